"""sync4d.recon: see the modules in this package."""

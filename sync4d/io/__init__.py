"""sync4d.io: see the modules in this package."""

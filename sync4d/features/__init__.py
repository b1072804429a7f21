"""sync4d.features: see the modules in this package."""

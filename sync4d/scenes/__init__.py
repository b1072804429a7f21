"""sync4d.scenes: see the modules in this package."""

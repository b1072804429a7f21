"""sync4d.sim: see the modules in this package."""

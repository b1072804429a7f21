"""sync4d.velocity: see the modules in this package."""

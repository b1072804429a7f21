"""sync4d.loggers: see the modules in this package."""

"""simulate / estimate / evaluate as library functions taking a config and returning a result."""

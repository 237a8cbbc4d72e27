"""Pure numpy/scipy math: no file or network I/O in this package."""

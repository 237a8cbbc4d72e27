"""Reading and writing MCAP logs and Rerun recordings."""

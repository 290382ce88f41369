"""What `higher-plot` and `higher-reproduce` both read: runs loaded from their folders, and matplotlib
set up for files. Below both, so neither imports the other."""

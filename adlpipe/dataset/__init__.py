"""What is stored and how it is read back: the HDF5 schema and its opener (schema.py), torch datasets and target
statistics (loader.py)."""

"""Curating a stored dataset: the doctor, its checks and signals, edits, and the verification of an HDF5 file."""

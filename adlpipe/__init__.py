"""adlpipe: ADL robot-manipulation bags -> HDF5 -> flow-matching / diffusion / BC policies -> evaluation."""

__version__ = "0.1.0"

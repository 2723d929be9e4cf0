"""OpenCL C sources of the emdflow engine (installed as package data of ``emdflow.kernels``)."""

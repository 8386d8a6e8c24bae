"""endowave-cl: EndoWave 4D Gaussian splatting with hand-written OpenCL kernels."""
__version__ = "0.1.0"

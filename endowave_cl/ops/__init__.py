"""Host ops: each pairs an OpenCL forward kernel with its adjoint (see docs/ARCHITECTURE.md)."""

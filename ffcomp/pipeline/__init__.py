"""Compositions of stages (the only place that strings kernels together); one module per flow."""

"""Gaussian-process machinery: kernels, the numerically stable factorization, GPy training
and the incremental live posterior."""

"""refsim: a reference solver for needle insertion and tissue laceration.

After Perrusi, Baksic and Courtecuisse, "Interactive Finite Element model of needle insertion and laceration",
Eurographics 2021. See docs/architecture.md for the layers.

``import refsim`` imports no dependency: each subpackage imports what it uses, numba with its kernel cache on
the first import of a module that defines kernels (:mod:`refsim.kernel_cache`).
"""

__version__ = "0.1.0"

__all__ = ["__version__"]

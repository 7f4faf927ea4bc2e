"""refsim: a reference solver for needle insertion and tissue laceration.

After Perrusi, Baksic and Courtecuisse, "Interactive Finite Element model of needle insertion and laceration",
Eurographics 2021. See DESIGN.md in docs/ for the architecture.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]

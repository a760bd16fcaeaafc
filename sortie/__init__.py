"""Sortie: distributed battlefield simulation service.

This package holds what every other package shares: the error root
(:mod:`sortie.errors`), the command line (:mod:`sortie.cli`) and the code
generated from ``proto/sortie/v1`` (:mod:`sortie.v1`).
"""

__version__ = "0.1.0"

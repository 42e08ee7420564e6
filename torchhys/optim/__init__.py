"""Optimizers: conjugate gradient with Powell-Beale restarts and its line searches."""

from torchhys.optim.line_search import LineSearchResult
from torchhys.optim.powell_beale import PowellBealeCG

__all__ = ["LineSearchResult", "PowellBealeCG"]

"""Identification: the ``fit_*`` and ``select_*`` functions and the penalised least squares
they share."""

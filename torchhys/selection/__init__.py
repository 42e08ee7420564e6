"""Model selection on tensors: which model of a record's device fits it, chosen by
cross-validation and fitted, without Lightning (:func:`select`).

- :mod:`torchhys.selection.run`: :func:`select`, :class:`Selection`;
- :mod:`torchhys.selection.candidates`: one candidate built, fitted (its readout solved by
  least squares where it is affine) and scored;
- :mod:`torchhys.selection.folds`: blocked, rolling-origin and leave-one-recording-out folds;
- :mod:`torchhys.selection.scores`: scores, the selection rules, the table;
- :mod:`torchhys.selection.jobs`: candidates in parallel processes, the time budget;
- :mod:`torchhys.selection.coverage`: what no split of a record can show.
"""

from torchhys.selection.candidates import MODEL_DEFAULTS
from torchhys.selection.run import Progress, Selection, select
from torchhys.selection.scores import RULES, CandidateScore, best, standard_error

__all__ = ["MODEL_DEFAULTS", "RULES", "CandidateScore", "Progress", "Selection", "best", "select",
           "standard_error"]

"""``make reproduce`` (``python -m torchhys.reproduce``): the paper's simulation experiment
(Section 5.2), trained through Lightning (:mod:`~torchhys.reproduce.experiment`), and the
figure of its plant (:mod:`~torchhys.reproduce._plant`)."""

"""Reading the data a fit is made on, without Lightning: recorded CSV/NPZ tables
(:mod:`~torchhys.data.tables`), their recordings (:mod:`~torchhys.data.files`) and the
stages' splits (:mod:`~torchhys.data.splits`).
"""

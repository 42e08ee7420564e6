"""The ``torchhys`` command line: ``torchhys fit|validate|test|predict|export``.

:mod:`torchhys.cli.main` is the console script's entry point; the training commands are a
LightningCLI (:mod:`torchhys.cli.train`), ``export`` is :mod:`torchhys.cli.export`.
"""

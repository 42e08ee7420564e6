"""``python -m torchhys.reproduce``: :func:`torchhys.reproduce.experiment.main`."""

from torchhys.reproduce.experiment import main

if __name__ == "__main__":
    main()

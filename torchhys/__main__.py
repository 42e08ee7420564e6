"""``python -m torchhys``: the ``torchhys`` command (:mod:`torchhys.cli.main`)."""

from torchhys.cli.main import main

if __name__ == "__main__":
    main()

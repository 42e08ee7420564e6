"""``python -m torchhys``: the ``torchhys`` command (:mod:`torchhys._command`)."""

from torchhys._command import main

if __name__ == "__main__":
    main()

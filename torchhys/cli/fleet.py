"""``torchhys fleet``: a fleet of devices identified in one command, each as ``torchhys fit``
identifies it alone (:func:`torchhys.fleet.identify_fleet`; docs/fleet.md)::

    torchhys fleet --config configs/measured.yaml --data.path 'devices/*.csv' \\
        [--data.device_column COL] [--cluster tcp://HOST:8786 | SCHEDULER_FILE] \\
        [--root runs/fleet] [--workers N] [--retries 2] [--timeout 10] \\
        [--resume runs/fleet/fleet_0] [--device-timeout SECONDS] \\
        [any option of fit: --trainer.max_epochs 5 ...]

The fleet's own options are taken out here; every other option (``--config`` files, the
data, model and trainer options, and the command's ``--import``, ``--import-path``,
``--threads``, ``--quiet``) is given to each device's ``fit`` as it is. The per-device
lines go to stderr (not with ``--quiet``), the summary to stdout. A user error (an empty
glob, a cluster that does not answer, a bad option) is one line, ``torchhys fleet: error:
...``, exit status 2; devices that fail are rows of the report, the status 0 while at
least one device is identified (1 when none is).

The fleet's options:

- ``--data.path GLOB|FILE``: the devices' recordings, a file each (named by its stem), or
  one file with ``--data.device_column COL`` naming each row's device;
- ``--cluster tcp://HOST:8786|SCHEDULER_FILE``: an existing Dask cluster (default: a local
  cluster of ``--workers N`` processes, one per usable core);
- ``--root DIR``: where ``fleet_N/`` goes (default runs/fleet); ``--resume DIR``: an earlier
  fleet's folder, its finished devices kept;
- ``--retries N``: retries of a device whose task failed or whose worker died (default 2);
- ``--timeout S``: seconds to wait for the cluster's scheduler (default 10);
- ``--device-timeout S``: the longest wait for the next device to finish (default
  ``TORCHHYS_TIMEOUT_S``, else six hours).

Then ``torchhys export --fleet ROOT/fleet_N --format c`` exports every device (docs/fleet.md).
"""

from __future__ import annotations

from collections.abc import Sequence

from torchhys.cli.errors import report_user_error
from torchhys.cli.plain_text import plain
from torchhys.cli.quiet import QUIET_FLAG

__all__ = ["FLEET_OPTIONS", "main", "split_fleet_options"]

FLEET_OPTIONS = {"--data.path": "data", "--data.device_column": "device_column",
                 "--cluster": "cluster", "--root": "root", "--workers": "workers",
                 "--retries": "retries", "--timeout": "timeout", "--resume": "resume",
                 "--device-timeout": "device_timeout"}
"""The fleet's own options and :func:`~torchhys.fleet.identify_fleet`'s argument of each."""

_TYPES = {"workers": int, "retries": int, "timeout": float, "device_timeout": float}


def split_fleet_options(argv: Sequence[str]) -> tuple[dict[str, object], list[str], list[str]]:
    """``argv`` cut into the fleet's options (by argument name, typed), the ``--config``
    files, and the rest (``fit``'s options).

    Raises:
        ValueError: an option without its value, a value of the wrong kind, no
            ``--data.path``.
    """
    options: dict[str, object] = {}
    configs: list[str] = []
    rest: list[str] = []
    it = iter(argv)
    for a in it:
        name, eq, value = a.partition("=")
        if name in FLEET_OPTIONS or name == "--config":
            if not eq:
                value = next(it, None)
                if value is None or value.startswith("--"):
                    raise ValueError(f"{name} needs a value")
            if name == "--config":
                configs.append(value)
                continue
            key = FLEET_OPTIONS[name]
            kind = _TYPES.get(key, str)
            try:
                options[key] = kind(value)
            except ValueError:
                raise ValueError(f"{name} must be a {kind.__name__}, got {value!r}") from None
        else:
            rest.append(a)
    if "data" not in options:
        raise ValueError("torchhys fleet needs --data.path: a glob of the devices' recordings "
                         "('devices/*.csv') or one file with --data.device_column")
    return options, configs, rest


def main(argv: Sequence[str], *, traceback: bool = False) -> int:
    """Run ``torchhys fleet`` (:func:`torchhys.cli.main.main` calls it); its exit status."""
    if any(a in ("-h", "--help", "--help-all") for a in argv):
        print(plain(__doc__ or "").strip())
        return 0
    quiet = QUIET_FLAG in argv
    try:
        from torchhys.fleet import identify_fleet

        options, configs, rest = split_fleet_options(argv)
        result = identify_fleet(options.pop("data"), config=configs or None, args=rest,
                                say=(lambda s: None) if quiet else None,
                                **options)  # type: ignore[arg-type]
    except Exception as exc:
        if not report_user_error("torchhys fleet", exc, traceback):
            raise
        return 2
    print(result.text)
    print(f"report: {result.csv}" + (f", loops: {result.picture}" if result.picture else ""),
          flush=True)
    return 0 if len(result.failed) < len(result.rows) else 1

"""The ``torchhys`` command: ``torchhys fit|validate|test|predict --config FILE``.

A :class:`lightning.pytorch.cli.LightningCLI` over
:class:`torchhys.training.InverseHysteresisModule` and
:class:`torchhys.training.HysteresisDataModule`: every option can be set in the YAML config or
overridden on the command line (``--data.path``, ``--trainer.max_epochs``,
``--trainer.default_root_dir``, ``--model.optimizer`` ...); ``--ckpt_path`` resumes a fit or
picks the weights to evaluate. Logs (CSV) and checkpoints go under the run's
``trainer.default_root_dir``; ``predict`` also writes ``predictions.csv`` there.
"""

from __future__ import annotations

import sys
import warnings

from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningCLI

from torchhys.training.callbacks import PredictionWriter
from torchhys.training.data import HysteresisDataModule
from torchhys.training.module import InverseHysteresisModule

__all__ = ["TorchhysCLI", "main"]

_DESCRIPTION = (
    "Train and evaluate inverse-hysteresis models. Subcommands: fit, validate, test, "
    "predict (LightningCLI; any option can be overridden, e.g. --trainer.max_epochs=10), "
    "export (a trained checkpoint to a deployable compensator: torchhys export --help)."
)


class TorchhysCLI(LightningCLI):
    """LightningCLI with a CSV logger under ``default_root_dir`` (unless one is configured),
    a :class:`~torchhys.training.callbacks.PredictionWriter` (``--predictions.filename``) and a
    checkpoint after every training epoch (``--checkpoint.*``; ``last.ckpt`` to resume)."""

    def add_arguments_to_parser(self, parser) -> None:  # noqa: ANN001 (jsonargparse parser)
        parser.add_lightning_class_args(PredictionWriter, "predictions")
        # Full-batch runs often validate rarely: save at the end of every training epoch.
        parser.add_lightning_class_args(ModelCheckpoint, "checkpoint")
        parser.set_defaults({"checkpoint.save_on_train_epoch_end": True,
                             "checkpoint.save_last": True})

    def before_instantiate_classes(self) -> None:
        cfg = self.config[self.subcommand] if self.subcommand else self.config
        trainer = cfg["trainer"]
        if trainer.get("logger") in (None, True):
            root = trainer.get("default_root_dir") or "."
            trainer["logger"] = {
                "class_path": "lightning.pytorch.loggers.CSVLogger",
                "init_args": {"save_dir": root, "name": "logs"},
            }


def main(argv: list[str] | None = None) -> None:
    """Entry point of the ``torchhys`` console script.

    Args:
        argv: command-line arguments without the program name (``sys.argv[1:]`` if None).
    """
    args = sys.argv[1:] if argv is None else list(argv)
    if args and args[0] == "export":
        from torchhys.training.export_cmd import main as export_main

        raise SystemExit(export_main(args[1:]))
    # Full-batch training: one sequence per step, so loader workers would only add start-up.
    warnings.filterwarnings("ignore", ".*does not have many workers.*")
    TorchhysCLI(
        InverseHysteresisModule,
        HysteresisDataModule,
        args=argv,
        seed_everything_default=0,
        save_config_kwargs={"overwrite": True},
        trainer_defaults={"log_every_n_steps": 1},
        parser_kwargs={"description": _DESCRIPTION},
    )


if __name__ == "__main__":
    main()

"""The ``torchhys`` command: ``torchhys fit|validate|test|predict --config FILE``.

A :class:`lightning.pytorch.cli.LightningCLI` over
:class:`torchhys.training.InverseHysteresisModule` and
:class:`torchhys.training.HysteresisDataModule`: every option can be set in the YAML config or
overridden on the command line (``--data.path``, ``--trainer.max_epochs``,
``--trainer.default_root_dir``, ``--model.optimizer`` ...); ``--ckpt_path`` resumes a fit or
picks the weights to evaluate (read and checked before anything is written). Logs (CSV) and
checkpoints go under ``<default_root_dir>/logs/version_<N>`` (``trainer.default_root_dir``);
``predict`` also writes ``predictions.csv`` in ``default_root_dir``.

An error in the user's files, options or data (a missing or malformed data file, a bad
config value, a damaged checkpoint ...) is printed as one line, ``torchhys fit: error:
<message>``, and the command exits with status 2; ``--traceback`` (or
``TORCHHYS_TRACEBACK=1``) shows its traceback. Any other exception is a bug in torchhys and
keeps its traceback (:mod:`torchhys.cli.errors`).

Model selection (``fit`` only): ``model.select`` lists candidates, each a dict of model
arguments that replace the ``model`` section's (an argument of the command, not of
:class:`~torchhys.training.InverseHysteresisModule`: it is taken out of the model section
before the module is built)::

    model:
      operator: [{fit: pi_ls, n_widths: 20}]
      hidden: 8
      select:                                   # or --model.select '[{...}, ...]'
        - {}                                    # the section as it is
        - {operator: [{fit: plays, n: 8}], hidden: 16}
        - {operator: null}                      # the plain network
      select_cv: null                           # k: blocked cross-validation instead,
                                                # recording: leave one recording out
      select_cv_mode: null                      # "rolling": validate each block (recording)
                                                # on a fit of those before it only
      select_rule: null                         # "1se": the first unless beaten by > 1 s.e.
      select_jobs: null                         # n: candidates in n processes at a time
      select_budget_s: null                     # s: no candidate starts after s seconds

Every candidate is trained from the same seed with the same trainer settings (one progress
line before and after each: :mod:`torchhys.selection.progress`) and scored by its validation
MSE; the table goes to ``selection.csv`` in the run's own ``logs/version_<N>`` folder
(reserved atomically: concurrent runs keep theirs); the chosen candidate is fitted once, by
:func:`torchhys.selection.select` (its readout solved or trained), and the final Lightning
``fit`` in that folder logs, validates and checkpoints it without training it again
(``last.ckpt`` as a plain ``fit``'s). A trainer section that ``select`` cannot honour
scores every candidate and fits the chosen one by Lightning runs instead, and says why.
The rules (validation split, blocked, rolling and leave-one-recording-out cross-validation,
the one-standard-error rule) are stated once, in
docs/training.md ("Model selection on validation data"); the code is in
:mod:`torchhys.selection` (:func:`torchhys.cli.selection.select_record`: when; else Lightning
runs, :mod:`torchhys.training.selection`). ``validate``, ``test`` and ``predict`` ignore
``model.select``, and so does a ``fit --ckpt_path`` that resumes.

The options of the command itself (``--import``, ``--threads``, ``--quiet``,
``--traceback``) are taken out before LightningCLI reads the rest (:mod:`torchhys.cli.main`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from jsonargparse import ArgumentError, Namespace, get_loader
from lightning.pytorch import Trainer, seed_everything
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningCLI
from lightning.pytorch.utilities import rank_zero_only, rank_zero_warn

from torchhys.cli import selection as cli_selection
from torchhys.cli.checks import check_config_files, check_optimizer_switch
from torchhys.cli.ckpt_paths import check_ckpt_path
from torchhys.cli.config_yaml import check_config_aliases
from torchhys.cli.config_yaml import install as install_bounded_yaml
from torchhys.cli.configs import require_config, resolve_config_names
from torchhys.cli.errors import TRACEBACK_ENV, config_errors, report_user_error
from torchhys.cli.help_format import PlainArgumentParser, parser_kwargs
from torchhys.cli.loggers import expand_logger_names, prepare_loggers
from torchhys.cli.negative_numbers import accept_negative_numbers
from torchhys.cli.quiet import quiet_requested
from torchhys.cli.run_dirs import RUN_DIR_ENV, reserve_run_dir
from torchhys.cli.selection import say_lightning, select_record, use_fitted, write_fold_logs
from torchhys.data.files import watch_files
from torchhys.identification.specs import build_operators
from torchhys.optim.named import check_optimizer_kwargs
from torchhys.selection import scores
from torchhys.selection import select as select_candidates
from torchhys.selection.candidates import is_direct, model_base
from torchhys.selection.coverage import warn_coverage
from torchhys.selection.folds import describe_cv
from torchhys.selection.jobs import check_budget, check_jobs, usable_cores
from torchhys.selection.progress import SelectionProgress
from torchhys.training.callbacks import BaselineComparison, PredictionWriter
from torchhys.training.data import HysteresisDataModule
from torchhys.training.interrupts import (
    Interrupted,
    SigtermCheckpoint,
    report_interrupt,
    signals_raise,
)
from torchhys.training.module import InverseHysteresisModule
from torchhys.training.report import FitReport
from torchhys.training.run_checkpoint import RunCheckpoint

install_bounded_yaml()  # aliases in configs expand to a bounded size

__all__ = ["TorchhysCLI", "read_config", "run"]

_DESCRIPTION = (
    "Train and evaluate inverse-hysteresis models. Subcommands: fit, validate, test, "
    "predict (LightningCLI; any option can be overridden, e.g. --trainer.max_epochs=10), "
    "export (a trained checkpoint to a deployable compensator: torchhys export --help). "
    "torchhys configs lists the shipped configs, each usable by name (--config measured); "
    "torchhys --version."
)



class TorchhysCLI(LightningCLI):
    """LightningCLI with a CSV logger under ``default_root_dir`` (unless one is configured),
    a :class:`~torchhys.training.callbacks.PredictionWriter` (``--predictions.filename``), a
    :class:`~torchhys.training.callbacks.BaselineComparison` in ``test`` (the line and the
    memoryless polynomial fitted on the training split, ``--baselines.max_degree``), a
    :class:`~torchhys.training.report.FitReport` in ``fit`` (``fit_report.png``: the
    fitted loop and the validation tracking beside the baselines), a
    checkpoint after every training epoch, one file, ``last.ckpt`` (``--checkpoint.*``;
    ``--checkpoint.save_top_k`` with ``--checkpoint.monitor`` to keep the best too), and
    model selection by validation in ``fit`` (``--model.select``, ``--model.select_cv``: see
    the module docstring)."""

    def init_parser(self, **kwargs: Any) -> Any:  # each parser: --model.lr -1e-3 a value
        return accept_negative_numbers(super().init_parser(**kwargs))

    def add_arguments_to_parser(self, parser) -> None:  # noqa: ANN001 (jsonargparse parser)
        parser.add_lightning_class_args(PredictionWriter, "predictions")
        # test: the straight line and the memoryless polynomial beside the model
        parser.add_lightning_class_args(BaselineComparison, "baselines")
        # fit: the fitted loop and the validation tracking beside them (fit_report.png)
        parser.add_lightning_class_args(FitReport, "fit_report")
        # Full-batch runs often validate rarely: save at the end of every training epoch.
        parser.add_lightning_class_args(RunCheckpoint, "checkpoint")
        # checkpoints written to a temporary file beside them and renamed: a full disk or a
        # kill while saving leaves the previous last.ckpt whole (torchhys/training/checkpoint_io.py)
        # one file per run, last.ckpt: RunCheckpoint's defaults (save_last, save_top_k 0;
        # --checkpoint.save_top_k 1 and a --checkpoint.monitor keep the best as well)
        parser.set_defaults({"checkpoint.save_on_train_epoch_end": True,
                             "trainer.plugins": [{"class_path": cli_selection.ATOMIC_IO}]})
        # Arguments of the command kept in the model section, removed before the module is
        # built (see _select).
        for name, kind, text in cli_selection.ARGUMENTS:
            parser.add_argument(f"--model.{name}", type=kind, default=None, help=text)
        # the network's operating conditions: as many as the data's condition columns
        parser.link_arguments("data.condition_columns", "model.n_conditions",
                              compute_fn=_count_conditions)

    def parse_arguments(self, parser, args) -> None:  # noqa: ANN001 (LightningCLI's)
        """Parse, then read and check ``--ckpt_path`` (a file) before anything is written:
        a missing or damaged checkpoint is a one-line error, with no run folder left. A
        ``--config`` that is no config, and ``--model.optimizer`` with the config's kwargs
        of another optimizer, are one-line errors too (:mod:`torchhys.cli.checks`)."""
        argv = sys.argv[1:] if args is None else args
        if isinstance(argv, list):
            check_config_files(argv)
        super().parse_arguments(parser, args)
        sub = self.config.get("subcommand")
        if isinstance(argv, list) and sub:
            check_optimizer_switch(self.config[sub], argv)
        if sub and isinstance(self.config[sub].get("ckpt_path"), str | os.PathLike):
            # a file read and checked, a URL refused, 'last' the newest earlier run's
            self.config[sub]["ckpt_path"] = check_ckpt_path(self.config[sub]["ckpt_path"],
                                                            self.config[sub])

    def before_instantiate_classes(self) -> None:
        self._run_dir: tuple[Path, int | str | None] | None = None
        cfg = self.config[self.subcommand] if self.subcommand else self.config
        root = cfg["trainer"].get("default_root_dir") or "."
        prepare_loggers(cfg["trainer"].get("logger"), root)  # csv, tensorboard: the default's
        self._select()
        cfg = self.config[self.subcommand] if self.subcommand else self.config
        trainer = cfg["trainer"]
        if trainer.get("logger") in (None, True):
            trainer["logger"] = {
                "class_path": "lightning.pytorch.loggers.CSVLogger",
                "init_args": {"save_dir": root, "name": "logs"},
            }
        if self._run_dir is not None and self._run_dir[1] is not None:
            # the final fit logs (and checkpoints) in the folder model selection reserved
            trainer["logger"]["init_args"]["version"] = self._run_dir[1]

    def instantiate_classes(self) -> None:
        """LightningCLI's, a TypeError while building the classes being a user error."""
        with config_errors():
            super().instantiate_classes()

    def instantiate_trainer(self, **kwargs: Any) -> Trainer:
        """LightningCLI's, with :class:`~torchhys.training.interrupts.SigtermCheckpoint`."""
        trainer = super().instantiate_trainer(**kwargs)
        trainer.callbacks.append(SigtermCheckpoint())
        return trainer

    def before_fit(self) -> None:
        """A plain fit warns as model selection does (once) when the training record holds
        less than one closed loop or loops of one amplitude
        (:func:`~torchhys.selection.coverage.coverage_warning`)."""
        if not self._selected:
            warn_coverage(self.datamodule, "fit")
        elif self._fitted is not None:  # fitted by select: logged, not trained again
            use_fitted(self.model, self._fitted)

    # --- model selection ------------------------------------------------------------------
    def _select(self) -> None:
        """Take ``model.select``/``select_cv``/``select_cv_mode``/``select_rule`` out of the
        config; in ``fit``, score the
        candidates and put the chosen one's model section in their place."""
        self._selected = False  # set once run_selection has run (and warned, before_fit)
        self._fitted: torch.nn.Module | None = None  # the chosen network, fitted by select
        sub = self.subcommand
        cfg = self.config[sub] if sub else self.config
        options = _pop_select(cfg)
        select, cv, mode, rule = (options[k] for k in ("select", "select_cv", "select_cv_mode",
                                                       "select_rule"))
        if select is None:
            for key, value in options.items():
                if value is not None:
                    raise ValueError(f"model.{key}={value!r} needs model.select (the candidates)")
            return
        if sub != "fit" or cfg.get("ckpt_path"):
            if not cfg.get("ckpt_path"):
                rank_zero_warn(f"model.select is used by fit only; {sub} ignores it and builds "
                               "the model section as it is (give --ckpt_path)")
            elif sub == "fit":
                rank_zero_warn("fit --ckpt_path resumes the checkpoint's model: model.select "
                               "is ignored")
            return
        if cfg["model"].get("net") is not None:
            raise ValueError("model.select builds each candidate's network from the model "
                             "arguments, but model.net gives a ready network: remove it")
        with config_errors():  # a TypeError here is in the candidates, not in training
            candidates = cli_selection.check_candidates(
                select, cli_selection.model_arguments(self._model_class), cv=cv, mode=mode)
            jobs, budget = check_jobs(options["select_jobs"]), check_budget(
                options["select_budget_s"])
            configs = [self._candidate_config(i, c) for i, c in enumerate(candidates)]
        seed = cfg.get("seed_everything")
        if isinstance(seed, bool) or seed is None:  # unseeded: still one seed for all
            seed = seed_everything(workers=True)
        # the run's own version folder, reserved now: concurrent runs into the same
        # default_root_dir keep their tables apart; the final fit logs there too
        folder, version = reserve_run_dir(cfg["trainer"])
        self._run_dir = (folder, version)

        progress = SelectionProgress(candidates, cv if isinstance(cv, int) else None,
                                     quiet=quiet_requested())
        if options["select_jobs"] == "auto" and _on_gpu(cfg["trainer"]):
            jobs = 1  # CUDA does not survive a fork
        if jobs > 1 and cli_selection.distributed(cfg["trainer"]):
            # a rank that forks selection workers hangs: each worker would start ranks of
            # its own; every rank runs the candidates one after another instead
            jobs = 1
            if not quiet_requested():
                print("torchhys fit: model.select_jobs falls back to 1 under a distributed or "
                      "multi-device trainer (no fork from inside a rank)", file=sys.stderr,
                      flush=True)
        jobs = min(jobs, len(candidates))
        if jobs > 1 and not quiet_requested():
            print(f"torchhys fit: candidates in {jobs} processes at a time, torch threads "
                  f"{max(1, torch.get_num_threads() // jobs)} each (model.select_jobs="
                  f"{options['select_jobs']}; {usable_cores()} usable cores)",
                  file=sys.stderr, flush=True)

        def build(i: int, fold: int | None) -> tuple[Any, Any, Trainer]:
            progress.starts(i, fold)
            return self._instantiate_run(configs[i], seed, folder / "selection", i, fold)

        try:
            with _quiet_lightning(), signals_raise():  # SIGTERM, Ctrl-C: Interrupted
                direct, reason = select_record(configs, sub, cv)
                if direct is not None:  # the library's selection (select_record: when)
                    result = select_candidates(
                        candidates, direct.x, direct.y, base=model_base(cfg["model"]),
                        warmup=direct.warmup, mask=direct.mask, cv=cv, mode=mode,
                        rule=rule or "min", jobs=jobs, budget_s=budget, dtype=direct.dtype,
                        seed=seed, epochs=direct.epochs, seconds=direct.seconds,
                        progress=progress, source=direct.source, refit=False,
                        val=direct.val_record(), conditions=direct.conditions)
                    scored = result.scores
                    write_fold_logs(scored, folder / "selection")
                else:  # a trainer section select cannot honour: a Lightning run each
                    from torchhys.training.selection import run_selection

                    say_lightning(reason)
                    scored = run_selection(candidates, build, cv=cv, mode=mode, jobs=jobs,
                                           budget_s=budget, report=progress.scored)
        except BaseException:
            progress.close()
            with contextlib.suppress(OSError):  # stopped before any candidate logged
                folder.rmdir()
            raise
        progress.close()
        self._selected = True
        chosen = scores.best(scored, rule or "min")
        _report(scored, chosen, folder / "selection.csv", describe_cv(cv, mode),
                rule or "min")
        # fitted once by select after its table is written (a trained readout limited by
        # max_time is left to the final fit: recording it, that would run on for
        # max_time without a step); the final fit records it without training it again
        if direct is not None and (direct.seconds is None or is_direct(result.spec)):
            with signals_raise():
                self._fitted = result.fit()
        self.config = configs[chosen.index]
        self.__dict__.pop("config_dump", None)  # the module's hyperparameters: the choice
        seed_everything(seed, workers=True)  # the fit starts as the candidate's run did

    def _candidate_config(self, index: int, overrides: dict[str, Any]) -> Namespace:
        """The whole config with the candidate's model arguments, parsed (type-checked)."""
        parser = self._parser(self.subcommand)
        exit_on_error, parser.exit_on_error = parser.exit_on_error, False
        try:
            cfg = parser.parse_object({"model": overrides}, self.config[self.subcommand])
        except ArgumentError as err:
            raise ValueError(f"model.select[{index}] {overrides}: {err}") from None
        finally:
            parser.exit_on_error = exit_on_error
        model = cfg["model"]
        try:  # the operators' specs and the optimizer's kwargs, before any candidate trains
            build_operators(model["operator"], model["operator_kwargs"])
            check_optimizer_kwargs(model["optimizer"], model["optimizer_kwargs"])
        except (ValueError, TypeError) as err:
            raise ValueError(f"model.select[{index}] {overrides}: {err}") from None
        _pop_select(cfg)
        full = self.config.clone()
        full[self.subcommand] = cfg
        return full

    def _instantiate_run(self, config: Namespace, seed: int, root: Path, index: int,
                         fold: int | None) -> tuple[Any, Any, Trainer]:
        """Fresh, seeded model, datamodule and trainer of a candidate's run: the config's
        trainer settings, without checkpoints, logging (CSV) under ``root``."""
        run = config.clone()
        trainer = run[self.subcommand]["trainer"]
        if trainer.get("logger") is not False:
            name = f"candidate_{index}" + ("" if fold is None else f"/fold_{fold}")
            trainer["logger"] = {"class_path": "lightning.pytorch.loggers.CSVLogger",
                                 "init_args": {"save_dir": str(root), "name": name}}
        trainer["enable_checkpointing"] = False
        # one line per candidate instead (_progress): no bar, summary or seed message per run
        trainer["enable_progress_bar"] = False
        trainer["enable_model_summary"] = False
        seed_everything(seed, workers=True, verbose=False)
        self.config = run  # the instantiator takes the module's hyperparameters from it
        self.__dict__.pop("config_dump", None)
        instantiate = getattr(self.parser, "instantiate", None) or self.parser.instantiate_classes
        self.config_init = instantiate(run)
        self.model = self._get(self.config_init, "model")
        self._add_configure_optimizers_method_to_model(self.subcommand)
        kwargs = dict(self._get(self.config_init, "trainer"))
        kwargs["callbacks"] = [c for c in kwargs.get("callbacks") or []
                               if not isinstance(c, ModelCheckpoint)]
        return self.model, self._get(self.config_init, "data"), self.trainer_class(**kwargs)


def _count_conditions(columns: Any) -> int:
    """``model.n_conditions`` of ``data.condition_columns`` (None: 0)."""
    return 0 if columns is None else len(columns)


def _on_gpu(trainer: Any) -> bool:
    """Whether the trainer section may run on a GPU (an accelerator other than ``cpu`` on a
    machine with CUDA)."""
    return str(trainer.get("accelerator") or "auto") != "cpu" and torch.cuda.is_available()


def _pop_select(cfg: Namespace) -> dict[str, Any]:
    """Remove the options of model selection (``model.select``, ``model.select_cv``, ...:
    :data:`~torchhys.cli.selection.ARGUMENTS`) from a (subcommand's) config; their
    values by name."""
    values = {}
    for name, _, _ in cli_selection.ARGUMENTS:
        values[name] = cfg.get(f"model.{name}")
        if f"model.{name}" in cfg:
            del cfg[f"model.{name}"]
    return values


@contextlib.contextmanager
def _quiet_lightning() -> Iterator[None]:
    """Lightning's informational messages (devices found, seeds, tips) off while the
    candidates train, once per run each; its warnings and errors still show."""
    loggers = [logging.getLogger(name) for name in ("lightning.pytorch", "lightning.fabric")]
    levels = [log.level for log in loggers]
    for log in loggers:
        log.setLevel(max(log.getEffectiveLevel(), logging.WARNING))
    try:
        yield
    finally:
        for log, level in zip(loggers, levels, strict=True):
            log.setLevel(level)


@rank_zero_only
def _report(scored: list[scores.CandidateScore], chosen: scores.CandidateScore,
            path: Path, how: str, rule: str) -> None:
    scores.write_table(scored, chosen, path)
    if rule == "1se":
        how += " (one-standard-error rule)"
    print(f"model selection on {how}:\n{scores.format_table(scored, chosen)}\n"
          f"selected candidate {chosen.index}: {scores.config_json(chosen.overrides)} "
          f"(val_mse {chosen.val_mse:.6g}); table written to {path}", flush=True)


def read_config(path: str | Path) -> dict[str, Any]:
    """A config file's sections, parsed with the YAML loader of ``torchhys fit --config``
    (jsonargparse's), so that ``ridge: 1e-8`` is the number 1e-8 (YAML 1.1, which PyYAML's
    ``safe_load`` follows, reads it as the string '1e-8'). Only the loader is shared: no
    defaults are filled in and nothing is checked. For scripts that build a config's model
    outside the command (the benchmarks).

    Raises:
        ValueError: the file does not hold a mapping (naming the path).
    """
    with open(path) as f:
        cfg = get_loader("yaml")(f.read())
    if not isinstance(cfg, dict):
        raise ValueError(f"config {path}: expected a mapping of sections (model:, data:, "
                         f"trainer:), got {type(cfg).__name__}")
    return cfg


def run(args: list[str], *, from_sys_argv: bool, traceback: bool, help_all: bool = False) -> None:
    """Run ``torchhys fit|validate|test|predict`` (:func:`torchhys.cli.main.main` calls it
    once it has taken out the command's own options).

    Args:
        args: the arguments LightningCLI reads (the subcommand and its options).
        from_sys_argv: the command runs from ``sys.argv``: LightningCLI reads ``args`` there
            (DDP relaunches each rank with it), and ``traceback`` is passed to the ranks'
            processes as ``TORCHHYS_TRACEBACK``.
        traceback: user errors keep their traceback (``--traceback``).
        help_all: ``--help`` shows every option, not the most used (:mod:`torchhys.cli.help`).

    Raises:
        SystemExit: 2 on a user error, 128 + the signal's number on an interrupt (model
            selection), and as LightningCLI exits (usage errors, ``--help``).
    """
    try:
        args = expand_logger_names(args)  # --trainer.logger tensorboard: its class path
        args = resolve_config_names(args)  # --config measured: the shipped file
        require_config(args)
    except ValueError as exc:
        if not report_user_error(f"torchhys {args[0] if args else ''}".strip(), exc, traceback):
            raise
        raise SystemExit(2) from None
    if from_sys_argv:
        sys.argv[1:] = args
        if traceback:
            os.environ[TRACEBACK_ENV] = "1"  # for the ranks' processes
    sub = next((a for a in args if a in TorchhysCLI.subcommands()), None)
    prog = f"torchhys {sub}" if sub else "torchhys"
    # Full-batch training: one sequence per step, so loader workers would only add start-up.
    warnings.filterwarnings("ignore", ".*does not have many workers.*")
    try:
        check_config_aliases(args)  # before the parser expands them
        watch_files()  # a data file read again in this command holds what it held first
        TorchhysCLI(
            InverseHysteresisModule,
            HysteresisDataModule,
            args=None if from_sys_argv else args,
            seed_everything_default=0,
            save_config_kwargs={"overwrite": True},
            trainer_defaults={"log_every_n_steps": 1},
            parser_kwargs=parser_kwargs(_DESCRIPTION, TorchhysCLI.subcommands(), full=help_all),
            parser_class=PlainArgumentParser,  # a class's help (--trainer.callbacks.help) too
        )
    except (Interrupted, KeyboardInterrupt) as exc:  # a signal during model selection
        if traceback:
            raise
        raise SystemExit(report_interrupt(prog, exc)) from None
    except Exception as exc:
        if not report_user_error(prog, exc, traceback):
            raise
        raise SystemExit(2) from None
    finally:
        os.environ.pop(RUN_DIR_ENV, None)
        watch_files(False)

"""``torchhys fit`` with ``model.select``: the candidates of a config scored, chosen and
fitted by :func:`torchhys.selection.select` on the training split.

:func:`select_record` says whether a run is one ``select`` scores as Lightning runs of its
candidates would (every readout solved by least squares, or a trainer section that asks for
nothing ``select`` does not do: :func:`trainer_reason`) and reads its training split once
(with a hold-out, ``select_cv: null``, also its validation split); the command then calls
:func:`torchhys.selection.select`, which scores the candidates and fits the chosen one once
(its readout solved or trained), and hands that network to the final Lightning run
(:func:`use_fitted`), which logs, validates and checkpoints it without training it again.
Other runs (callbacks, gradient clipping, a GPU ...) are scored and fitted by Lightning runs
(:func:`torchhys.training.selection.run_selection`, then the final fit): ``select`` would not
train their candidates as their trainer section does; the command says why
(:func:`say_lightning`).
"""

from __future__ import annotations

import csv
import inspect
import math
import sys
from collections.abc import Mapping, Sequence
from datetime import timedelta
from pathlib import Path
from typing import Any, Literal, NamedTuple

import torch
from lightning.pytorch.utilities import rank_zero_only
from torch import Tensor

from torchhys._checks import check_choice, check_int
from torchhys.cli.quiet import quiet_requested
from torchhys.selection.candidates import candidate_spec, is_direct, model_base, steps_readout
from torchhys.selection.folds import CONDITION, CV_MODES, RECORDING
from torchhys.selection.run import Record, record
from torchhys.selection.scores import CandidateScore
from torchhys.training.data import HysteresisDataModule

__all__ = ["ARGUMENTS", "ATOMIC_IO", "SelectRecord", "check_candidates", "model_arguments",
           "say_lightning", "select_record", "trainer_reason", "use_fitted",
           "write_fold_logs"]

_DTYPES = {"64-true": torch.float64, "64": torch.float64, "32-true": torch.float32,
           "32": torch.float32}


class SelectRecord(NamedTuple):
    """A training split for :func:`torchhys.selection.select`, and with a hold-out
    (``select_cv: null``) the validation split's batch ``(x, y, warmup, mask)``; the
    training steps (``trainer.max_epochs``) and seconds (``trainer.max_time``) of a
    candidate whose readout is trained."""

    x: Tensor
    y: Tensor
    warmup: Tensor
    mask: Tensor
    dtype: torch.dtype
    source: str
    val: tuple[Tensor, ...] | None = None
    epochs: int = 1000
    seconds: float | None = None
    conditions: Tensor | None = None
    """The training rows' operating conditions (rows, time, n), or None."""

    def record(self) -> Record:
        """The training split as :func:`torchhys.selection.select` reads it."""
        return record(self.x, self.y, warmup=self.warmup, mask=self.mask, source=self.source,
                      conditions=self.conditions)

    def val_record(self) -> Record | None:
        """The validation split as a record (None under cross-validation): each row runs
        from its recording's start (a time split: the training part as its warm-up) and is
        scored on the validation samples only, as a Lightning validation scores it."""
        if self.val is None:
            return None
        x, y, warmup, mask = self.val[:4]
        return record(x, y, warmup=warmup, mask=mask.to(torch.bool), source=self.source,
                      conditions=self.val[4] if len(self.val) == 5 else None)


def one_device(trainer: Any) -> bool:
    """Whether the trainer section runs on one device of one node without a distributed
    strategy."""
    devices = trainer.get("devices")
    return (str(devices) in ("1", "[0]") and int(trainer.get("num_nodes") or 1) == 1
            and str(trainer.get("strategy") or "auto") == "auto")


def distributed(trainer: Any) -> bool:
    """Whether the trainer section may start several ranks: a strategy other than ``auto``,
    several nodes, or devices other than one (``auto`` on one node counts as one)."""
    auto = (str(trainer.get("devices")) == "auto" and int(trainer.get("num_nodes") or 1) == 1
            and str(trainer.get("strategy") or "auto") == "auto")
    return not (one_device(trainer) or auto)


_NO_EFFECT = frozenset({
    "logger", "default_root_dir", "enable_progress_bar", "enable_model_summary",
    "enable_checkpointing", "check_val_every_n_epoch", "val_check_interval",
    "limit_val_batches", "limit_test_batches", "limit_predict_batches", "num_sanity_val_steps",
    "log_every_n_steps", "deterministic", "benchmark", "inference_mode", "barebones",
    "use_distributed_sampler", "reload_dataloaders_every_n_epochs", "detect_anomaly",
    "profiler", "max_epochs", "max_time", "precision", "accelerator", "devices", "num_nodes",
    "strategy", "plugins"})
"""Trainer options that :func:`torchhys.selection.select` honours (``max_epochs`` as its
``epochs``, ``max_time`` as its ``seconds``, the precision as its dtype, one CPU device:
checked by :func:`trainer_reason`) or that do not change a candidate's fitted weights
(logging, progress, the Lightning run's own validation)."""

ATOMIC_IO = "torchhys.training.checkpoint_io.AtomicCheckpointIO"
"""The checkpoint plugin the command installs (``trainer.plugins``): it writes files, not
weights, so a run holding it is still one ``select`` trains."""


def _seconds(max_time: Any) -> float | None:
    """``trainer.max_time`` in seconds (``"DD:HH:MM:SS"`` or a dict of ``days``,
    ``hours``, ``minutes``, ``seconds``; None: none); ValueError where it is neither."""
    if max_time is None:
        return None
    if isinstance(max_time, str):
        parts = [float(p) for p in max_time.split(":")]
        if len(parts) != 4:
            raise ValueError(max_time)
        return float(timedelta(days=parts[0], hours=parts[1], minutes=parts[2],
                               seconds=parts[3]).total_seconds())
    if isinstance(max_time, Mapping):
        return float(timedelta(**dict(max_time)).total_seconds())
    raise ValueError(max_time)


def trainer_reason(trainer: Any) -> str | None:
    """Why :func:`torchhys.selection.select` cannot train the candidates as the config's
    trainer section would (one line naming the option), or None: it asks for nothing but
    the steps (``max_epochs``, default 1000 as Lightning's; ``max_time``), float32 or
    float64 on one CPU device, and options that change no fitted weight (:data:`_NO_EFFECT`).

    ``select`` trains each candidate full batch by its optimizer, one step an epoch, as the
    Lightning module does (the same seed gives the same weights); it runs no callbacks (an
    early stop, a learning-rate monitor, a user's own), no gradient clipping or accumulation,
    no mixed precision, no step or batch limits, and no device but the CPU: a run that asks
    for one of those trains its candidates by Lightning."""
    from lightning.pytorch import Trainer

    if str(trainer.get("precision") or "32-true") not in _DTYPES:
        return f"trainer.precision={trainer.get('precision')!r} (select trains in float32 " \
               "or float64)"
    accelerator = str(trainer.get("accelerator") or "auto")
    if accelerator != "cpu" and (accelerator != "auto" or torch.cuda.is_available()):
        return f"trainer.accelerator={accelerator!r} (select trains on the CPU)"
    if not (one_device(trainer) or str(trainer.get("devices")) == "auto"):
        return (f"trainer.devices={trainer.get('devices')!r}, num_nodes="
                f"{trainer.get('num_nodes')!r}, strategy={trainer.get('strategy')!r} (select "
                "trains on one device, strategy 'auto')")
    epochs = trainer.get("max_epochs")
    try:
        seconds = _seconds(trainer.get("max_time"))
    except (ValueError, TypeError):
        return f"trainer.max_time={trainer.get('max_time')!r}"
    if epochs is not None and not (epochs >= 1 or epochs == -1 and seconds is not None):
        return (f"trainer.max_epochs={epochs!r} (select trains a whole number of epochs >= 1, "
                "or with max_time, -1: until then)")
    for plugin in trainer.get("plugins") or []:
        path = plugin.get("class_path") if hasattr(plugin, "get") else plugin
        if path != ATOMIC_IO:
            return f"trainer.plugins holds {path!r}"
    defaults = {name: p.default for name, p in
                inspect.signature(Trainer.__init__).parameters.items()}
    for key, value in trainer.items():
        if key in _NO_EFFECT or key not in defaults:
            continue
        default = defaults[key]
        if value != default and not (value in (None, []) and default in (None, [])):
            return f"trainer.{key}={value!r} (select runs no {key})"
    return None


def select_record(configs: list[Any], sub: str, cv: object) -> tuple[SelectRecord | None, str]:
    """The training split of a ``fit`` that :func:`torchhys.selection.select` scores as
    Lightning runs of its candidates ``configs`` would, from a
    :class:`~torchhys.training.HysteresisDataModule` (with ``cv`` None, the hold-out, also
    its validation split, checked: :func:`~torchhys.training.selection.check_holdout`),
    and ``""``; or None and why not (the candidates then train by Lightning).

    ``select`` takes a run whose candidates are all solved directly (an identity activation
    over fixed operators, a closure optimizer: their training a least-squares problem), on
    one device in float32 or float64; or any candidates where the trainer section asks for
    nothing ``select`` does not do (:func:`trainer_reason`)."""
    cfg = configs[0][sub]
    trainer = cfg["trainer"]
    dtype = _DTYPES.get(str(trainer.get("precision") or "32-true"))
    epochs = trainer.get("max_epochs")
    reason = trainer_reason(trainer)
    if reason is not None:
        if (dtype is None or not one_device(trainer)
                or not steps_readout(epochs, trainer.get("limit_train_batches"))):
            return None, reason
        for i, config in enumerate(configs):
            if not is_direct(candidate_spec(model_base(config[sub]["model"]), {})):
                return None, f"{reason}, and model.select[{i}] is trained"
    data = cfg["data"]
    args = data.as_dict() if hasattr(data, "as_dict") else dict(data)
    if "class_path" in args:  # a datamodule of its own: not read here
        return None, f"data.class_path={args['class_path']!r} (select reads the data of a " \
                     "HysteresisDataModule)"
    datamodule = HysteresisDataModule(**args)
    datamodule.setup("fit")
    if cv is None:  # the same error as a Lightning hold-out, before the training split's
        from torchhys.training.selection import check_holdout

        check_holdout(datamodule)
    datamodule.train_tensors()  # a constant column is the file's error, naming it
    batches = datamodule.batches("train")
    if not batches:
        return None, "no training batch"
    x, y, warmup, mask = batches[0][:4]
    conditions = batches[0][4] if len(batches[0]) == 5 else None
    source = getattr(datamodule, "source", "the data")
    if cv == RECORDING and x.shape[0] < 2:  # the library's error, in the config's names
        raise ValueError(
            f"model.select_cv={RECORDING!r} holds each training recording out once, but the "
            f"training split of {source} holds {x.shape[0]}: give several (data.split_by: "
            "recording with data.train_recordings, or several data.path files), or use "
            "blocked cross-validation inside the record (model.select_cv: k)")
    val = datamodule.batches("val")[0] if cv is None else None
    seconds = _seconds(trainer.get("max_time"))
    steps = (epochs if epochs is not None and epochs >= 1 else
             1000 if epochs is None and seconds is None else 2 ** 62)  # Lightning's
    if epochs in (None, -1) and seconds is not None and any(
            c[sub]["model"].get("schedule") for c in configs):
        return None, ("trainer.max_time without trainer.max_epochs, and a model.schedule "
                      "(Lightning decays it over one epoch)")
    return SelectRecord(x, y, warmup, mask.to(torch.bool), dtype or torch.float32, source,
                        val, steps, seconds, conditions), ""


def write_fold_logs(scores: Sequence[CandidateScore], root: Path) -> None:
    """Each scored fold's ``val_mse`` as the run's logs hold a trained fold's:
    ``root/candidate_<i>/fold_<j>/version_0/metrics.csv`` (``step,val_mse``; a hold-out's,
    without folds: ``root/candidate_<i>/version_0``); a fold that was not scored (a family
    that could not be fitted, not run) has none."""
    for score in scores:
        runs = ([(f"fold_{j}", m) for j, m in enumerate(score.folds)] if score.folds
                else [("", score.val_mse)])
        for name, mse in runs:
            if not math.isfinite(mse):
                continue
            folder = root / f"candidate_{score.index}" / name / "version_0"
            folder.mkdir(parents=True, exist_ok=True)
            with (folder / "metrics.csv").open("w", newline="") as fh:
                csv.writer(fh).writerows([["step", "val_mse"], [0, repr(mse)]])


def use_fitted(module: Any, net: torch.nn.Module) -> None:
    """Give the final fit's module the network :func:`torchhys.selection.select` fitted: its
    families, normalization and readout (solved or trained) kept; its optimizer sees no
    gradient and takes no step (the module's ``fitted``)."""
    module.net = net
    module.normalization_fitted.fill_(True)
    module.fitted = True


@rank_zero_only
def say_lightning(reason: str) -> None:
    """Say on stderr, unless ``--quiet``, why the candidates train through Lightning runs
    (:func:`select_record`'s reason): one line."""
    if reason and not quiet_requested():
        print(f"torchhys fit: model selection trained through Lightning: {reason}",
              file=sys.stderr, flush=True)


ARGUMENTS: list[tuple[str, Any, str]] = [
    ("select", list[dict[str, Any]] | None,
     "fit: candidate model configurations, each a dict of model arguments that replace the "
     "model section's; the one of lowest validation MSE is fitted (table in "
     "<default_root_dir>/logs/version_<N>/selection.csv)"),
    ("select_cv", int | Literal["recording", "condition"] | None,
     "fit with model.select: score the candidates by blocked cross-validation with this many "
     "contiguous blocks of the training part, 'recording': hold each training recording "
     "out once, or 'condition': hold each operating condition's recordings out once "
     "(data.condition_columns; default: on the validation split)"),
    ("select_cv_mode", Literal["blocked", "rolling"] | None,
     "fit with model.select_cv: 'blocked' (default) holds each block (recording) out once, "
     "fitted on all the others; 'rolling' validates each block (recording) after the first "
     "on a fit of those before it only"),
    ("select_rule", Literal["min", "1se"] | None,
     "fit with model.select: 'min' (default) chooses the lowest validation MSE, '1se' the "
     "first candidate (the baseline) when within one standard error of it"),
    ("select_jobs", int | Literal["auto"] | None,
     "fit with model.select: candidates scored at a time, each in a process of its own, "
     "torch's threads divided among them; 'auto': the usable cores, at most 4 (default 1)"),
    ("select_budget_s", float | None,
     "fit with model.select: seconds after which no further candidate starts; those not "
     "started are skipped, said in the table (default: none)"),
]
"""The command's options of model selection (``--model.NAME``): name, type, help."""


def model_arguments(model_class: type) -> list[str]:
    """The arguments a candidate may set: ``model_class.__init__``'s, except ``net`` (a
    ready network would ignore the others)."""
    params = inspect.signature(model_class.__init__).parameters.values()
    return [p.name for p in params if p.name not in ("self", "net")
            and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]


def check_candidates(select: object, valid: Sequence[str], *,
                     cv: object = None, mode: object = None) -> list[dict[str, Any]]:
    """The candidates as dicts, checked.

    Raises:
        ValueError: an empty list, a key that is not a model argument (the message names
            it and lists ``valid``), ``cv`` neither an int >= 2 nor ``"recording"``,
            ``mode`` not one of :data:`~torchhys.selection.folds.CV_MODES` (None:
            ``"blocked"``) or given without ``cv``.
        TypeError: ``select`` not a list, a candidate not a dict.
    """
    if isinstance(select, (str, bytes, Mapping)) or not isinstance(select, Sequence):
        raise TypeError(
            f"model.select must be a list of candidates (dicts of model arguments), got "
            f"{type(select).__name__} {select!r}"
        )
    if not select:
        raise ValueError(
            "model.select is empty: list the candidates, each a dict of model arguments "
            "that replace the model section's (e.g. [{hidden: 4}, {operator: null}]), or "
            "leave select out"
        )
    candidates = []
    for k, cand in enumerate(select):
        if not isinstance(cand, Mapping):
            raise TypeError(
                f"model.select[{k}] must be a dict of model arguments, got "
                f"{type(cand).__name__} {cand!r}"
            )
        unknown = sorted(set(cand) - set(valid))
        if unknown:
            verb = "is not a model argument" if len(unknown) == 1 else "are not model arguments"
            raise ValueError(
                f"model.select[{k}]: {', '.join(map(repr, unknown))} {verb}; valid: "
                f"{list(valid)}"
            )
        candidates.append(dict(cand))
    if cv is not None and cv not in (RECORDING, CONDITION):
        if isinstance(cv, str):
            raise ValueError(f"model.select_cv must be an int >= 2 (blocked cross-validation), "
                             f"{RECORDING!r} (leave one recording out) or {CONDITION!r} "
                             f"(leave one condition out), got {cv!r}")
        check_int(cv, "model.select_cv", minimum=2)
    if mode is not None:
        check_choice(mode, "model.select_cv_mode", CV_MODES)
        if cv is None:
            raise ValueError(f"model.select_cv_mode={mode!r} needs model.select_cv (k blocks, "
                             f"or {RECORDING!r})")
    return candidates

"""``InverseHysteresisModule``: Lightning training of :class:`torchhys.InverseHysteresisNet`."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import lightning as L
import torch
import torch.nn.functional as F
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities import rank_zero_warn
from torch import Tensor, nn
from torchmetrics import MeanSquaredError

from torchhys import InverseHysteresisNet
from torchhys._checks import check_choice
from torchhys._finite import check_learning_rate, check_normalization, check_training
from torchhys.identification.specs import build_operators, fit_data_dependent
from torchhys.init import initialize
from torchhys.optim.named import (
    CLOSURE_OPTIMIZERS,
    OPTIMIZERS,
    check_optimizer_kwargs,
    optimizer_arguments,
)
from torchhys.protocols import Network, SequenceModel, check_network, check_sequence_model

__all__ = ["InverseHysteresisModule"]

_FULL_PRECISION = ("32-true", "64-true", "32", "64")


Batch = tuple[Tensor, ...]
"""``(x, y)``, ``(x, y, warmup)`` or ``(x, y, warmup, mask)``: x, y (batch, time);
``warmup`` leading samples of the sequence (the preceding record, or the training warm-up)
are excluded from the loss and the metrics; a boolean ``mask`` (batch, time), when given,
marks the scored samples instead (rows of several recordings: each row's own warm-up, no
padding), and the loss is the mean over them."""

Scorer = Callable[[Tensor], Tensor]
"""Selects the scored samples of a (batch, time) tensor."""


def _unpack(batch: Batch) -> tuple[Tensor, Tensor, Scorer, Tensor | None]:
    """``(x, y, scored, conditions)``: ``scored`` picks the samples of the loss and the
    metrics; the batch's operating conditions (its fifth member) or None."""
    if len(batch) == 2:
        return batch[0], batch[1], lambda v: v, None
    if len(batch) in (4, 5):
        x, y, _, mask = batch[:4]
        mask = mask.to(torch.bool)
        return x, y, lambda v: v[mask], batch[4] if len(batch) == 5 else None
    x, y, warmup = batch
    first = int(warmup.reshape(-1)[0]) if isinstance(warmup, Tensor) else int(warmup)
    return x, y, lambda v: v[..., first:], None


def check_closure_trainer(trainer: Any, optimizer: str) -> None:
    """Raise ``ValueError`` for trainer options that break a closure optimizer's line search.

    Gradient clipping would clip every trial point, gradient accumulation would mix trial
    points, and mixed precision makes the loss too coarse for a line search (a gradient
    scaler, as with ``16-mixed`` on a GPU, cannot take a closure at all).
    """
    where = f"optimizer={optimizer!r} (a closure optimizer with a line search)"
    clip = getattr(trainer, "gradient_clip_val", None)
    if clip is not None and clip > 0:
        raise ValueError(
            f"Trainer(gradient_clip_val={clip}) cannot be combined with {where}: clipping "
            "would distort every line-search trial. Remove gradient_clip_val, or use Adam."
        )
    accumulate = getattr(trainer, "accumulate_grad_batches", 1)
    if accumulate != 1:
        raise ValueError(
            f"Trainer(accumulate_grad_batches={accumulate}) cannot be combined with {where}: "
            "the closure computes the full-batch loss itself. Remove accumulate_grad_batches."
        )
    plugin = getattr(trainer, "precision_plugin", None)
    precision = str(getattr(trainer, "precision", "32-true"))
    if getattr(plugin, "scaler", None) is not None or precision not in _FULL_PRECISION:
        scaler = " uses a gradient scaler, which cannot take a closure, and" if getattr(
            plugin, "scaler", None) is not None else ""
        raise ValueError(
            f"Trainer(precision={precision!r}){scaler} cannot be combined with {where}: a "
            "line search needs a full-precision loss (16-mixed falls back to bf16-mixed on "
            "the CPU). Use precision='32-true' or '64-true'."
        )


class InverseHysteresisModule(L.LightningModule):
    """Train an inverse-hysteresis network (and any learnable ``a``) on full sequences.

    Batches are ``(x, y)`` of shape (batch, time): the inverse model's input (the plant's
    output) and target (the plant's input), in physical units, optionally with a warm-up
    and a mask of the scored samples (see :data:`Batch`: rows of several recordings, padded,
    each from a fresh state; the loss is the mean over the scored samples of all rows, so
    closure optimizers see every training recording in one full batch). The network's
    normalization is fitted on the training data of the attached
    :class:`torchhys.training.HysteresisDataModule`
    (or any datamodule with ``train_tensors() -> (x, y)``) in :meth:`setup`, and saved in
    checkpoints with the weights.

    Optimizers: ``"adam"`` (automatic optimization: gradient clipping, accumulation and
    mixed precision work as usual), ``"cg"`` (:class:`torchhys.optim.PowellBealeCG`) and
    ``"lbfgs"``. The closure optimizers run with manual optimization: the closure computes
    the full-batch loss and its gradient (all-reduced across DDP ranks, so every rank's line
    search sees the same values), and the logged ``train_loss`` is the loss at the
    parameters after the step, not an average over line-search trials. Combining them with
    gradient clipping, accumulation or mixed precision raises ``ValueError`` when the
    module is attached to a ``Trainer`` for fitting.

    Operators are registered operators, given by name or as specs ``{"name": ...,
    **options}`` (``eiho``, ``zhao_tan``, ...), or model families fitted on the training data,
    ``{"fit": ..., **options}`` (``plays``: play operators of the input; ``pi_ls``: the
    least-squares Prandtl-Ishlinskii model of the target from the input; ``preisach``,
    ``stop_pi``, ...: see :mod:`torchhys.identification.specs`). The families are fitted on the
    training split with the normalization, once, and saved in checkpoints.
    Per-segment EIHOs (``operator="eiho_segment"``, not causal) get the batch's
    targets as ``target``. Operator outputs that depend on no trainable parameter are
    computed once per batch (and cached across epochs), not in every closure call.

    Args:
        net: a ready network (an ``nn.Module`` with the members of
            :class:`torchhys.protocols.Network`, as :class:`torchhys.InverseHysteresisNet`
            has), or a sequence model (:class:`torchhys.protocols.SequenceModel`: a
            :class:`torchhys.compose.Composed`, trained end to end on its output, its
            ranges recorded in :meth:`setup`); when given,
            ``operator``, ``hidden``, ``activation``, ``operator_kwargs`` are ignored and
            ``load_from_checkpoint`` needs it passed again (a sequence model given by the
            command's config, ``class_path`` and ``init_args``, is saved as that spec).
        operator: ``"eiho"``, ``"zhao_tan"``, a spec dict such as ``{"name": "eiho",
            "rule": "dominant"}``, ``{"fit": "pi_ls", "n_widths": 30}`` or ``{"fit": "plays",
            "n": 16}``, a list of those, or None (plain network).
        hidden: hidden units.
        activation: hidden activation (``"sigmoid"`` in the paper).
        operator_kwargs: keyword arguments of the operators given by name only (e.g.
            ``{"a_formula": "sqrt"}``); spec dicts carry their own.
        init: ``"nguyen_widrow"`` or ``"default"`` (PyTorch's initialization).
        n_conditions: operating conditions per sample of the data (the datamodule's
            ``condition_columns``; the command line links them).
        condition_degree: None, a network that does not see the conditions; k >= 1, a
            network that takes them (:class:`~torchhys.InverseHysteresisNet`'s
            ``n_conditions``, ``condition_degree``).
        optimizer: ``"adam"``, ``"cg"`` or ``"lbfgs"``.
        lr: learning rate of Adam and LBFGS (CG has no learning rate).
        optimizer_kwargs: further keyword arguments of the optimizer.
        schedule: ``None`` or ``"cosine"`` (Adam only: cosine decay of ``lr`` to 0 over
            ``trainer.max_epochs``).
    """

    def __init__(
        self, net: nn.Module | None = None, *,
        operator: str | dict[str, Any] | list[str | dict[str, Any]] | None = "eiho",
        hidden: int = 168, activation: str = "sigmoid", operator_kwargs: dict | None = None,
        init: str = "nguyen_widrow", optimizer: str = "cg", lr: float = 1e-2,
        optimizer_kwargs: dict | None = None, schedule: str | None = None,
        n_conditions: int = 0, condition_degree: int | None = None,
    ) -> None:
        super().__init__()
        if condition_degree is not None and not n_conditions:
            raise ValueError(f"condition_degree={condition_degree}: the network takes operating "
                             "conditions, but the data has none (data.condition_columns)")
        check_choice(optimizer, "optimizer", sorted(OPTIMIZERS))
        check_optimizer_kwargs(optimizer, optimizer_kwargs)
        if schedule not in (None, "cosine") or (schedule and optimizer in CLOSURE_OPTIMIZERS):
            raise ValueError(
                f"schedule must be None or 'cosine' (with optimizer='adam'), got {schedule!r} "
                f"with optimizer={optimizer!r}"
            )
        self._sequence = isinstance(net, SequenceModel) and not isinstance(net, Network)
        with warnings.catch_warnings():  # a sequence model's spec: saved where it is one
            warnings.filterwarnings("ignore", message="Attribute 'net' is an instance")
            self.save_hyperparameters(ignore=[] if self._sequence else ["net"])
        if isinstance(self.hparams.get("net"), nn.Module):  # passed in built: no spec
            self.save_hyperparameters(ignore=["net"])
            self.hparams["net"] = None  # the checkpoint says so (torchhys export)
        self._fitters: dict = {}
        if self._sequence:
            net = check_sequence_model(net, "net")
        elif net is None:
            ops, self._fitters = build_operators(operator, operator_kwargs)
            net = InverseHysteresisNet(
                ops, hidden, activation=activation,
                n_conditions=n_conditions if condition_degree is not None else 0,
                condition_degree=condition_degree or 1)
            initialize(net, init)
        self.net = net if self._sequence else check_network(net, "net")
        self.optimizer_name = optimizer
        self.automatic_optimization = optimizer not in CLOSURE_OPTIMIZERS
        self.register_buffer("normalization_fitted", torch.tensor(False))
        self.val_mse, self.test_mse = MeanSquaredError(), MeanSquaredError()
        self._feature_cache: dict[str, tuple[Tensor, Tensor, Tensor]] = {}
        self._outside = (0, 0)  # (outside, total) input samples of a test or predict run
        self._last_loss: Tensor | None = None  # of the last training step (check_training)
        self.fitted = False
        """Set by ``torchhys fit`` after model selection fitted the network (its readout
        solved by least squares or trained: :func:`torchhys.selection.select`): the
        optimizer's step then sees no gradient and takes none (a closure optimizer's
        closure evaluates the loss without one; Adam's gradient is dropped before its step:
        :meth:`optimizer_step`), so the fit logs, validates and checkpoints the network as
        a trained one, with the weights unchanged
        (:func:`torchhys.cli.selection.use_fitted`)."""

    # --- checks -------------------------------------------------------------------------
    @property
    def trainer(self) -> L.Trainer:  # type: ignore[override]
        return L.LightningModule.trainer.fget(self)  # type: ignore[attr-defined]

    @trainer.setter
    def trainer(self, trainer: L.Trainer | None) -> None:
        # Attaching happens before Lightning's own loop checks: fail with a clear ValueError.
        if (
            trainer is not None and not self.automatic_optimization
            and getattr(getattr(trainer, "state", None), "fn", None) == TrainerFn.FITTING
        ):
            check_closure_trainer(trainer, self.optimizer_name)
        L.LightningModule.trainer.fset(self, trainer)  # type: ignore[attr-defined]

    # --- data-dependent set-up ----------------------------------------------------------
    def setup(self, stage: str) -> None:
        """Fit the data-dependent operators and the normalization on the datamodule's
        training part (once; a restored checkpoint then overwrites them)."""
        if bool(self.normalization_fitted):
            return
        dm = getattr(self.trainer, "datamodule", None)
        if dm is None or not hasattr(dm, "train_tensors"):
            return
        if str(getattr(self.trainer, "precision", "")).startswith("64"):
            self.net.double()  # as the precision plugin will: fit in float64 from the start
        x, y = dm.train_tensors()
        conditions = dm.train_conditions() if hasattr(dm, "train_conditions") else None
        self.fit_normalization(x, y, warmup=int(getattr(dm, "train_warmup", 0)),
                               mask=getattr(dm, "train_mask", None), conditions=conditions)

    def _takes_conditions(self) -> bool:
        return not self._sequence and bool(getattr(self.net, "n_conditions", 0))

    def _seen(self, conditions: Tensor | None) -> Tensor | None:
        """The batch's conditions where the network takes them, in its dtype (None: it does
        not; a network of conditions given a batch without is a one-line error)."""
        if not self._takes_conditions():
            return None
        if conditions is None:
            raise ValueError(f"the network takes {self.net.n_conditions} operating "
                             "condition(s), the data has none: set data.condition_columns")
        return conditions.to(self.dtype)

    def fit_normalization(self, x: Tensor, y: Tensor, *, warmup: int = 0,
                          mask: Tensor | None = None, conditions: Tensor | None = None) -> None:
        """Fit the data-dependent operators (``plays``, ``pi_ls``, the families; without the
        first ``warmup`` samples), then the network's normalization, to training data
        (physical units), (batch, time); with ``mask`` ((batch, time) bool) on its samples
        only (the states run through the others: a held-out block, a row's padding). A
        sequence model (:class:`~torchhys.protocols.SequenceModel`) records its ranges."""
        if self._sequence:
            self.net.record_ranges(x, y, mask=mask)
            self.normalization_fitted.fill_(True)
            return
        fit_data_dependent(self.net.operators, self._fitters, x, y, warmup=warmup, mask=mask)
        ref = next(iter(self.net.buffers()), None)
        dtype = ref.dtype if ref is not None else torch.get_default_dtype()
        c = self._seen(conditions)
        self.net.fit_normalization(x.to(dtype), y.to(dtype), mask=mask,
                                   conditions=None if c is None else c.to(dtype))
        check_normalization(self.net)  # data too large for the dtype: refused here
        self.normalization_fitted.fill_(True)
        self._feature_cache.clear()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Take the checkpoint's dtype before its weights are loaded (copying float64
        weights into a float32 module would round them), and drop cached features."""
        self._feature_cache.clear()
        dtypes = {v.dtype for k, v in (checkpoint.get("state_dict") or {}).items()
                  if k.startswith("net.") and isinstance(v, Tensor) and v.is_floating_point()}
        if len(dtypes) == 1:
            self.to(dtypes.pop())

    # --- the model ----------------------------------------------------------------------
    def _fixed_operators(self) -> bool:
        if self._sequence:
            return False
        return not any(p.requires_grad for p in self.net.operators.parameters())

    def _features(self, x: Tensor, y: Tensor, key: str,
                  conditions: Tensor | None = None) -> Tensor:
        """Operator features of (x, y) (and the conditions), cached when they depend on no
        trainable parameter."""
        cached = self._feature_cache.get(key)
        if cached is not None:
            cx, cy, cc, feats = cached
            if cx.shape == x.shape and cx.dtype == x.dtype and torch.equal(cx, x) and (
                torch.equal(cy, y)
            ) and (cc is None) == (conditions is None) and (
                    cc is None or torch.equal(cc, conditions)):
                return feats
        with torch.no_grad():
            feats, _ = self.net.features(x, target=y, conditions=conditions)
        self._feature_cache[key] = (x.detach().clone(), y.detach().clone(),
                                    None if conditions is None else conditions.clone(), feats)
        return feats

    def forward(self, x: Tensor, target: Tensor | None = None,
                conditions: Tensor | None = None) -> Tensor:
        """Model output for ``x`` (batch, time) or (time,); ``target`` for per-segment EIHOs;
        the conditions (batch, time, n) of a network that takes them."""
        if self._sequence:
            return self.net(x)
        return self.net(x, target=target, conditions=self._seen(conditions))[0]

    def _predict(self, x: Tensor, y: Tensor, key: str,
                 conditions: Tensor | None = None) -> Callable[[], Tensor]:
        """A function computing the prediction for the whole batch, (batch, time)."""
        x = x.to(self.dtype)
        y = y.to(self.dtype)
        c = self._seen(conditions)
        if self._fixed_operators():
            feats = self._features(x, y, key, c)
            return lambda: self.net.head(feats)
        return lambda: self.forward(x, y, c)

    def _global_mean(self, value: Tensor) -> Tensor:
        if self.trainer.world_size > 1:
            return self.trainer.strategy.reduce(value, reduce_op="mean")
        return value

    # --- training -----------------------------------------------------------------------
    def training_step(self, batch: Batch, batch_idx: int) -> Tensor | None:
        x, y, scored, c = _unpack(batch)
        y = y.to(self.dtype)
        full = self._predict(x, y, "train", c)

        def predict() -> Tensor:  # the warm-up samples only run the operator states
            return scored(full())

        y = scored(y)
        if self.automatic_optimization:
            loss = F.mse_loss(predict(), y)
            self._last_loss = loss.detach()
            self.log("train_loss", loss.detach(), on_step=False, on_epoch=True,
                     prog_bar=True, sync_dist=True)
            return loss
        opt = self.optimizers()

        def closure() -> Tensor:
            opt.zero_grad()
            loss = F.mse_loss(predict(), y)
            self.manual_backward(loss)  # DDP averages the gradients across ranks
            return self._global_mean(loss.detach())

        if self.fitted:  # fitted by select: the step sees no gradient and stops where it is
            def closure() -> Tensor:
                opt.zero_grad()
                with torch.no_grad():
                    return self._global_mean(F.mse_loss(predict(), y))

        opt.step(closure=closure)
        with torch.no_grad():
            loss = self._global_mean(F.mse_loss(predict(), y))
        self._last_loss = loss
        self.log("train_loss", loss, on_step=False, on_epoch=True, prog_bar=True)
        return None

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        """Stop a diverged fit: a loss or weights not finite after the step raise
        :class:`~torchhys._finite.DivergedError`, before a checkpoint is saved."""
        check_training(self, self._last_loss)

    def scored_outputs(self, batch: Batch, stage: str = "val") -> dict[str, Tensor]:
        """The batch's scored samples, each flat: ``input``, ``target``, ``prediction``, and
        ``conditions`` (samples, n) where the batch has them; without gradient, nothing
        logged (``stage``: the split the batch is of, ``"val"`` or ``"test"``)."""
        x, y, scored, c = _unpack(batch)
        y = y.to(self.dtype)
        with torch.no_grad():
            pred = self._predict(x, y, stage, c)()
        out = {"input": scored(x).reshape(-1), "target": scored(y).reshape(-1),
               "prediction": scored(pred).reshape(-1)}
        if c is not None:  # the scored samples' conditions, (samples, n)
            out["conditions"] = scored(c).reshape(-1, c.shape[-1])
        return out

    def _evaluate(self, batch: Batch, stage: str) -> dict[str, Tensor]:
        out = self.scored_outputs(batch, stage)
        metric = self.val_mse if stage == "val" else self.test_mse
        metric(out["prediction"], out["target"])
        self.log(f"{stage}_mse", metric, on_step=False, on_epoch=True, prog_bar=True)
        return out

    def validation_step(self, batch: Batch, batch_idx: int) -> None:
        self._evaluate(batch, "val")

    # --- inputs outside the training range (test, predict) ------------------------------
    def _count_outside(self, x: Tensor) -> None:
        """Add the samples of ``x`` (the scored ones, flat) outside the training input
        range to the running count (:meth:`_warn_outside`)."""
        lo, hi = float(self.net.in_min), float(self.net.in_max)
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return  # a network saved before the range was recorded
        outside = int(((x < lo) | (x > hi)).sum())
        self._outside = (self._outside[0] + outside, self._outside[1] + int(x.numel()))

    def _warn_outside(self, stage: str) -> None:
        """Warn once when some inputs of the stage lie outside the training input range:
        the model extrapolates there (an exported compensator clamps them)."""
        outside, total = self._outside
        self._outside = (0, 0)
        if outside:
            lo, hi = float(self.net.in_min), float(self.net.in_max)
            rank_zero_warn(
                f"{stage}: {outside} of {total} input samples ({100.0 * outside / total:.3g} %) "
                f"lie outside the training input range [{lo:.6g}, {hi:.6g}]: the model "
                "extrapolates there (an exported compensator clamps its input to that range "
                "widened by --input-margin and holds its direction)")

    def on_test_epoch_start(self) -> None:
        self._outside = (0, 0)

    def on_predict_epoch_start(self) -> None:
        self._outside = (0, 0)

    def on_test_epoch_end(self) -> None:
        self._warn_outside("test")

    def on_predict_epoch_end(self) -> None:
        self._warn_outside("predict")

    def test_step(self, batch: Batch, batch_idx: int) -> dict[str, Tensor]:
        """Log ``test_mse``; return the batch's scored samples, each flat: ``input``,
        ``target`` and ``prediction`` (for
        :class:`~torchhys.training.callbacks.BaselineComparison`). Inputs outside the
        training range are counted: a warning at the end says their share."""
        out = self._evaluate(batch, "test")
        self._count_outside(out["input"])
        return out

    def predict_step(self, batch: Batch, batch_idx: int) -> Tensor:
        """The model output over the whole batch, (batch, time). Inputs outside the
        training range are counted: a warning at the end says their share."""
        x, y, scored, c = _unpack(batch)
        self._count_outside(scored(x).reshape(-1))
        with torch.no_grad():
            return self._predict(x, y, "predict", c)()

    def optimizer_step(self, epoch: int, batch_idx: int, optimizer: Any,
                       optimizer_closure: Callable[[], Any] | None = None) -> None:
        """Lightning's, except for a network fitted by model selection (:attr:`fitted`,
        automatic optimization): the closure runs (the step's loss is logged), its gradient
        is dropped, and the optimizer's step sees none: every weight is kept."""
        if not self.fitted or optimizer_closure is None:
            super().optimizer_step(epoch, batch_idx, optimizer, optimizer_closure)
            return

        def closure() -> Any:
            loss = optimizer_closure()
            optimizer.zero_grad(set_to_none=True)
            return loss

        optimizer.step(closure=closure)

    def configure_optimizers(self) -> Any:
        if not self.automatic_optimization:
            check_closure_trainer(self.trainer, self.optimizer_name)
        kwargs = optimizer_arguments(self.optimizer_name, self.hparams.get("lr", 1e-2),
                                     self.hparams.get("optimizer_kwargs"))
        params = [p for p in self.parameters() if p.requires_grad]
        if "lr" in kwargs and params:  # one the weights' dtype holds (else a raw overflow)
            check_learning_rate(kwargs["lr"], params[0].dtype, self.optimizer_name)
        opt = OPTIMIZERS[self.optimizer_name](params, **kwargs)
        if self.hparams.get("schedule") == "cosine":
            epochs = max(int(self.trainer.max_epochs or 1), 1)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
            return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}
        return opt

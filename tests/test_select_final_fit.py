"""``torchhys fit`` with ``model.select``: the chosen candidate is fitted once, by
:func:`torchhys.selection.select`, and the final Lightning run records it (logs, validation,
checkpoints) without training it again; its checkpoint equals the one of the Lightning path
(a trainer option ``select`` does not honour) in weights and validation MSE; the Lightning
path says why it was taken."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch
from _training_helpers import DROP, cli, small_config, trainer

import torchhys.selection.candidates as candidates
import torchhys.selection.run as selection_run
from torchhys.training import HysteresisDataModule, InverseHysteresisModule

DATA = {"simulation": "paper", "t_end": 6.3, "split": [0.6, 0.2, 0.2], "warmup": 10}

ADAM = {"operator": None, "operator_kwargs": DROP, "hidden": 4, "activation": "tanh",
        "init": "default", "optimizer": "adam", "lr": 0.02, "optimizer_kwargs": DROP}
"""4 tanh units trained by Adam: no readout solved."""

CG = {"operator": None, "operator_kwargs": DROP, "hidden": 3, "activation": "sigmoid",
      "init": "default", "optimizer": "cg", "optimizer_kwargs": {"minstep": 0.0}}
"""3 sigmoid units trained by CG (a closure optimizer)."""

CASES = {
    "holdout-adam": ({**ADAM, "select_cv": DROP}, 6),
    "holdout-cg": ({**CG, "select_cv": DROP}, 4),
    "cv-adam-cosine": ({**ADAM, "schedule": "cosine", "select_cv": 2}, 5),
}
"""A model section (its candidates added) and ``max_epochs``."""

SELECT = [{}, {"operator": [{"fit": "plays", "n": 3}]}]


def _config(tmp_path: Path, case: str, **trainer_options: object) -> Path:
    model, epochs = CASES[case]
    return small_config(tmp_path, f"{case}.yaml",
                        trainer={"max_epochs": epochs, **trainer_options},
                        model={**model, "select": SELECT}, data=DATA)


def _fit(monkeypatch: pytest.MonkeyPatch, cfg: Path, root: Path, *args: str) -> Path:
    cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={root}", *args)
    return root / "logs/version_0/checkpoints/last.ckpt"


def _val_mse(ckpt: Path) -> float:
    module = InverseHysteresisModule.load_from_checkpoint(ckpt, weights_only=True)
    (res,) = trainer(limit_val_batches=None).validate(module, HysteresisDataModule(**DATA),
                                                      verbose=False)
    return res["val_mse"]


@pytest.fixture
def fits(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Every candidate fitted by select (one entry per fit)."""
    calls: list[int] = []
    fit = candidates.fit_candidate

    def counted(*args, **kwargs):
        calls.append(1)
        return fit(*args, **kwargs)

    monkeypatch.setattr(selection_run, "fit_candidate", counted)
    return calls


@pytest.mark.parametrize("case", sorted(CASES))
def test_the_chosen_candidate_is_fitted_once_as_the_lightning_path_fits_it(
        monkeypatch, capfd, tmp_path, fits, case) -> None:
    """The select path fits each candidate once per fold and the chosen one once more only
    under cross-validation (a hold-out's one fit is the final fit); its ``last.ckpt``
    equals the Lightning path's (``trainer.max_steps`` past the epochs: the same training,
    refused by select) in every weight and in val_mse, and loads for Lightning's validate;
    only the Lightning path says why it was taken (stderr, once)."""
    cv = CASES[case][0]["select_cv"]
    folds = 1 if cv is DROP else cv
    ours = _fit(monkeypatch, _config(tmp_path, case), tmp_path / "select")
    assert len(fits) == len(SELECT) * folds + (0 if cv is DROP else 1)
    assert "trained through Lightning" not in capfd.readouterr().err

    del fits[:]
    theirs = _fit(monkeypatch, _config(tmp_path, case, max_steps=1000), tmp_path / "lightning")
    assert not fits  # every candidate and the final fit trained by Lightning
    err = capfd.readouterr().err
    assert err.count("torchhys fit: model selection trained through Lightning: "
                     "trainer.max_steps=1000 (select runs no max_steps)") == 1

    def rows(root: Path) -> list[dict]:
        with (root / "logs/version_0/selection.csv").open() as fh:
            return list(csv.DictReader(fh))

    assert [r["selected"] for r in rows(tmp_path / "select")] == [
        r["selected"] for r in rows(tmp_path / "lightning")]
    a = torch.load(ours, weights_only=True)
    b = torch.load(theirs, weights_only=True)
    assert a["hyper_parameters"] == b["hyper_parameters"]
    assert (a["epoch"], a["global_step"]) == (b["epoch"], b["global_step"])
    assert a["state_dict"].keys() == b["state_dict"].keys()
    for key, value in a["state_dict"].items():
        torch.testing.assert_close(value, b["state_dict"][key], rtol=1e-9, atol=1e-12,
                                   msg=key)
    assert _val_mse(ours) == pytest.approx(_val_mse(theirs), rel=1e-9)
    # the run folder a plain fit leaves
    for root in (tmp_path / "select", tmp_path / "lightning"):
        folder = root / "logs/version_0"
        assert {p.name for p in folder.iterdir()} >= {
            "checkpoints", "config.yaml", "hparams.yaml", "metrics.csv", "selection.csv"}
        assert [p.name for p in (folder / "checkpoints").iterdir()] == ["last.ckpt"]
    # resumed, it trains on from its epoch and step count (Lightning's own loop state)
    epochs = CASES[case][1]
    with pytest.warns(UserWarning, match="resumes the checkpoint's model"):
        _fit(monkeypatch, _config(tmp_path, case), tmp_path / "select",
             f"--trainer.max_epochs={epochs + 2}", f"--ckpt_path={ours}")
    resumed = torch.load(tmp_path / "select/logs/version_1/checkpoints/last.ckpt",
                         weights_only=True)
    assert (resumed["epoch"], resumed["global_step"]) == (epochs + 1, epochs + 2)
    assert any(not torch.equal(v, resumed["state_dict"][k])
               for k, v in a["state_dict"].items() if k.endswith("weight"))


def test_the_lightning_path_reason_is_quiet_with_quiet(monkeypatch, capfd, tmp_path) -> None:
    """``--quiet`` (``TORCHHYS_QUIET``) keeps the Lightning path's line off stderr."""
    from torchhys.cli.selection import say_lightning

    monkeypatch.setenv("TORCHHYS_QUIET", "1")
    say_lightning("trainer.max_steps=3 (select runs no max_steps)")
    assert capfd.readouterr().err == ""
    monkeypatch.setenv("TORCHHYS_QUIET", "0")
    say_lightning("trainer.max_steps=3 (select runs no max_steps)")
    assert capfd.readouterr().err == ("torchhys fit: model selection trained through "
                                      "Lightning: trainer.max_steps=3 (select runs no "
                                      "max_steps)\n")


def test_the_final_run_takes_no_step(monkeypatch, tmp_path) -> None:
    """A network handed to the final fit (``use_fitted``) keeps every weight through an
    Adam run of several epochs (manual optimization, a closure without gradient)."""
    from torchhys.cli.selection import use_fitted

    torch.manual_seed(0)
    module = InverseHysteresisModule(operator=None, hidden=4, activation="tanh",
                                     optimizer="adam", lr=0.1)
    fresh = InverseHysteresisModule(operator=None, hidden=4, activation="tanh",
                                    optimizer="adam", lr=0.1)
    dm = HysteresisDataModule(**DATA)
    dm.setup("fit")
    x, y = dm.train_tensors()
    fresh.net.double()
    fresh.fit_normalization(x.double(), y.double())
    net = fresh.net
    before = {k: v.clone() for k, v in net.state_dict().items()}
    use_fitted(module, net)
    trainer(max_epochs=3).fit(module, datamodule=dm)
    for key, value in module.net.state_dict().items():
        assert torch.equal(value, before[key]), key
    # and a module not handed one trains (the check can fail)
    trainer(max_epochs=3).fit(fresh, datamodule=dm)
    assert any(not torch.equal(v, before[k]) for k, v in fresh.net.state_dict().items())


# --- the library: Selection.fit ------------------------------------------------------------
TANH = {"operator": None, "hidden": 3, "activation": "tanh", "optimizer": "adam", "lr": 0.05,
        "optimizer_kwargs": {}}
"""A trained readout (no least-squares solution)."""


def _loop(T: int = 300) -> tuple[torch.Tensor, torch.Tensor]:
    """A play of width 0.3 (a loop), as plain Python: (1, T) float64."""
    import math

    t = torch.linspace(0, 4 * math.pi, T, dtype=torch.float64)
    x = torch.sin(t) * (0.6 + 0.4 * torch.cos(t / 3))
    y, state = torch.empty_like(x), 0.0
    for i, v in enumerate(x.tolist()):
        state = min(max(state, v - 0.3), v + 0.3)
        y[i] = state
    return x[None], y[None]


@pytest.mark.parametrize("cv", [None, 2])
def test_selection_fit_is_the_chosen_candidate_fitted_once(fits, cv) -> None:
    """``refit=False`` then :meth:`Selection.fit` gives the network ``refit=True`` gives
    (every weight), the same one on each call; on a validation record of its own the chosen
    one's fit is its score's (no fit more than the candidates'), under cross-validation one
    fit more."""
    from torchhys.selection import select
    from torchhys.selection.run import Selection, record

    x, y = _loop()
    cut = 200
    options = {"warmup": 10, "warn_coverage": False, "epochs": 4, "seconds": None}
    if cv is None:
        mask = torch.zeros_like(x, dtype=torch.bool)
        mask[:, cut:] = True
        options["val"] = record(x, y, mask=mask)
    late = select([{}, TANH], x[:, :cut], y[:, :cut], cv=cv, refit=False, **options)
    assert late.model is None and len(fits) == 2 * (cv or 1)
    net = late.fit()
    assert late.fit() is net and len(fits) == 2 * (cv or 1) + (cv is not None)
    now = select([{}, TANH], x[:, :cut], y[:, :cut], cv=cv, **options)
    assert now.fit() is now.model and now.chosen.index == late.chosen.index
    for (key, a), b in zip(net.state_dict().items(), now.model.state_dict().values(),
                           strict=True):
        assert torch.equal(a, b), key
    with pytest.raises(ValueError, match="no record to fit on"):
        Selection(late.scores, late.chosen, late.spec, None, cv, None, "min").fit()


@pytest.mark.slow
def test_the_measured_config_fits_as_its_lightning_path(monkeypatch, tmp_path) -> None:
    """``configs/measured.yaml`` on ``examples/data/bouc_wen.csv``: the select path (the
    readout solved) and the Lightning path (``trainer.strategy: single_device``, refused by
    select: every candidate and fold a Lightning run, the readout trained by L-BFGS) choose
    the same candidate, fit the same family and normalization, and the same affine readout
    (the product of the hidden and output layers: L-BFGS trains the two factors) to
    rounding; their val_mse agree to 1e-6."""
    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)  # the config's data path is the repository's
    args = ("--model.select_jobs=1",)
    ours = _fit(monkeypatch, root / "configs/measured.yaml", tmp_path / "select", *args)
    theirs = _fit(monkeypatch, root / "configs/measured.yaml", tmp_path / "lightning", *args,
                  "--trainer.strategy=single_device")
    a = torch.load(ours, weights_only=True)
    b = torch.load(theirs, weights_only=True)
    assert a["hyper_parameters"] == b["hyper_parameters"]
    sa, sb = a["state_dict"], b["state_dict"]
    assert sa.keys() == sb.keys()
    layers = ("net.hidden.", "net.output.")
    for key in sa:
        if not key.startswith(layers):  # the family, the normalization: fitted alike
            torch.testing.assert_close(sa[key], sb[key], rtol=1e-10, atol=1e-12, msg=key)

    def affine(s: dict) -> torch.Tensor:
        w = s["net.output.weight"] @ s["net.hidden.weight"]
        c = s["net.output.weight"] @ s["net.hidden.bias"] + s["net.output.bias"]
        return torch.cat([w.flatten(), c.flatten()])

    torch.testing.assert_close(affine(sa), affine(sb), rtol=1e-5, atol=1e-7)

    def val_mse(root: Path) -> float:
        with (root / "logs/version_0/metrics.csv").open() as fh:
            return [float(r["val_mse"]) for r in csv.DictReader(fh) if r["val_mse"]][-1]

    assert val_mse(tmp_path / "select") == pytest.approx(val_mse(tmp_path / "lightning"),
                                                         rel=1e-6)

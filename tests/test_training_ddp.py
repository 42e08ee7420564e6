"""Full-batch CG under DDP (2 CPU processes, gloo) ends where a single process ends."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import lightning as L
import torch

from torchhys.training import HysteresisDataModule, InverseHysteresisModule


class SaveParameters(L.Callback):
    """Each rank writes its final parameters and CG state to ``<folder>/rank<k>.pt``."""

    def __init__(self, folder: str) -> None:
        self.folder = folder

    def on_train_end(self, trainer: L.Trainer, module: L.LightningModule) -> None:
        opt = trainer.optimizers[0]
        state = opt.state[opt.param_groups[0]["params"][0]]
        torch.save({"params": {k: v.detach().clone() for k, v in module.state_dict().items()},
                    "n_iter": state["n_iter"], "func_evals": state["func_evals"],
                    "d": state["d"]},
                   Path(self.folder) / f"rank{trainer.global_rank}.pt")


def run(folder: Path, devices: int) -> None:
    torch.set_num_threads(1)
    L.seed_everything(0, verbose=False)
    module = InverseHysteresisModule(operator="zhao_tan", hidden=8, optimizer="cg",
                                     operator_kwargs={"scale": 1.8},
                                     optimizer_kwargs={"minstep": 0.0})
    dm = HysteresisDataModule(t_end=2 * math.pi)
    folder.mkdir(parents=True, exist_ok=True)
    strategy = "ddp_spawn" if devices > 1 else "auto"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        trainer = L.Trainer(
            max_epochs=5, accelerator="cpu", devices=devices, strategy=strategy,
            precision="64-true", logger=False, enable_checkpointing=False,
            enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0,
            num_sanity_val_steps=0, callbacks=[SaveParameters(str(folder))],
        )
        try:
            trainer.fit(module, dm)
        except torch.multiprocessing.ProcessExitedException as err:
            # gloo's threads can abort a worker while the process exits ("terminate called
            # without an active exception"), after training: the results are written by then
            done = all((folder / f"rank{k}.pt").is_file() for k in range(devices))
            if err.signal_name != "SIGABRT" or not done:
                raise
            print(f"a DDP worker aborted at exit, after writing its results: {err}")


def test_ddp_cg_matches_a_single_process(tmp_path: Path) -> None:
    run(tmp_path / "single", devices=1)
    run(tmp_path / "ddp", devices=2)
    ref = torch.load(tmp_path / "single/rank0.pt", weights_only=True)
    ranks = [torch.load(tmp_path / f"ddp/rank{k}.pt", weights_only=True) for k in (0, 1)]
    assert ref["n_iter"] == 5
    for got in ranks:
        assert got["n_iter"] == ref["n_iter"] and got["func_evals"] == ref["func_evals"]
        for k, v in ref["params"].items():
            torch.testing.assert_close(got["params"][k], v, rtol=0, atol=1e-10)
        torch.testing.assert_close(got["d"], ref["d"], rtol=0, atol=1e-10)
    for k, v in ranks[0]["params"].items():  # the ranks agree exactly
        assert torch.equal(ranks[1]["params"][k], v)

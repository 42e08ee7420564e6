"""Simulated hysteretic plants."""

from torchhys.plants.bouc_wen import BoucWen, bouc_wen, bouc_wen_state
from torchhys.plants.paper import Simulation, fig6_simulation, paper_plant_widths, paper_simulation
from torchhys.plants.stage import PiezoStage, default_stage_hysteresis, second_order_zoh

__all__: list[str] = [
    "BoucWen",
    "bouc_wen",
    "bouc_wen_state",
    "Simulation",
    "fig6_simulation",
    "paper_plant_widths",
    "paper_simulation",
    "PiezoStage",
    "default_stage_hysteresis",
    "second_order_zoh",
]

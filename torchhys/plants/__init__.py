"""Simulated hysteretic plants."""

from torchhys.plants.paper import Simulation, fig6_simulation, paper_plant_widths, paper_simulation

__all__: list[str] = [
    "Simulation",
    "fig6_simulation",
    "paper_plant_widths",
    "paper_simulation",
]

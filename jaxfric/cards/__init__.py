"""Layer 5 (applications): equivalent drawbead data for stamping codes, computed from the blankholder scene
(:mod:`.bead`) and written in LS-DYNA's, OpenRadioss's and a CSV format (:mod:`.formats`)."""

from .bead import BeadCard, bead_card
from .formats import csv_table, line_friction, load_card, lsdyna_deck, radioss_interface, write_card

__all__ = ["BeadCard", "bead_card", "csv_table", "line_friction", "load_card", "lsdyna_deck", "radioss_interface",
           "write_card"]

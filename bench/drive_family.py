"""Randomised physical PMSM drives for validating the workbench: the public API of bench.family."""

from bench.family import (EFFECTS, EXCITATIONS, Drive, draw_drive, draw_effect, profile, revealable, simulate,
                          simulate_detail, truth, voltage_path)

__all__ = ["EFFECTS", "EXCITATIONS", "Drive", "draw_drive", "draw_effect", "profile", "revealable", "simulate",
           "simulate_detail", "truth", "voltage_path"]

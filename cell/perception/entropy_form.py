"""The forms of H_ROI (eq. 12), and the words that name each where H_ROI is shown (``cell jobs wait``'s
progress lines, servo.png's panel; the operator page's ``views/charts.js`` names them alike). A module of
its own, without NumPy, so that the command line's remote commands can name them."""

from __future__ import annotations

from typing import Literal

EntropyForm = Literal["paper", "observation_aware"]
"""How a voxel's uncertainty counts in H_ROI (eq. 12) and in the visual-servoing objective (eq. 9):
``paper``, eq. 8's H(p); ``observation_aware``, H(p) weighted by the information one more observation of
the voxel still gives (``cell.perception.occupancy.observation_weight`` of its counts; a departure,
``planners.vs.objective.entropy``)."""

ENTROPY_FORM_WORDS: dict[str, str] = {"paper": "eq. 8", "observation_aware": "observation-aware"}
"""Each form as a reader is told it."""


def h_roi_name(form: str) -> str:
    """``H_ROI (<the form's words>)``: H_ROI named with its form; a form this release does not know (a
    newer service's) by its own name."""
    return f"H_ROI ({ENTROPY_FORM_WORDS.get(form, form)})"

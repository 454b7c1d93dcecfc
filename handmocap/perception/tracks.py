"""One tracked hand (`Track`): its next crop, its last joints, its running side and how sure
DetNet is of it."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from handmocap.perception.crops import CropTransform
from handmocap.perception.one_euro import OneEuroFilter


def logit(p):
    p = np.clip(np.asarray(p, dtype=np.float64), 1e-4, 1 - 1e-4)
    return np.log(p / (1 - p))


# readings a track's running handedness is over (DetectorSettings.handedness_memory; chosen
# on training-side clips, docs/experiment_log.md, "Session 27")
HANDEDNESS_MEMORY = 60
# a reading's logit is clipped to +-this before it joins the running mean, so one sure reading
# cannot outweigh many (research/side_readings.py replays other bounds)
HANDEDNESS_LOGIT_BOUND = 6.0


@dataclass
class Track:
    """One tracked hand: its next crop and what was last seen of it."""
    track_id: int
    crop: CropTransform
    right_logit: float = 0.0          # running handedness evidence (> 0: right)
    samples: int = 0
    uv: np.ndarray | None = None
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    age: int = 0
    confidence: float = 0.0           # running mean heatmap peak: how much DetNet believes it is a hand
    birth_confidence: float | None = None   # its own birth threshold (None: the detector's)
    fixed_side: bool = False          # the side was given (HandDetector `handedness`): readings are ignored
    memory: int = HANDEDNESS_MEMORY   # handedness readings the running mean is over (`handedness_memory`)
    smoother: OneEuroFilter | None = None   # its published 2D joints' filter, in units of `unit`
    unit: float = 1.0                 # px: the hand's size when the filter started
    turn_checked: int = -1000         # its age at its last turn check (HandDetector `turn_check_below`)
    head_dir: np.ndarray | None = None   # running mean of the angle head's (cos, sin) in the frame (`turn_head_memory`)

    @property
    def is_right(self) -> bool:
        return self.right_logit >= 0.0

    def add_head_reading(self, p_right_seen, mirrored):
        """DetNet's handedness head p_right_seen (does the crop show a right hand) on a crop
        of this hand that was (mirrored) or was not flipped; NaN (not read) is no reading."""
        if np.isnan(p_right_seen):
            return
        self.add_handedness(1.0 - p_right_seen if mirrored else p_right_seen)

    def add_handedness(self, p_right, weight=1.0):
        """Running mean of logits over about the last `memory` observations."""
        if self.fixed_side:
            return
        n = min(self.samples + weight, self.memory)
        self.right_logit += (float(np.clip(logit(p_right), -HANDEDNESS_LOGIT_BOUND, HANDEDNESS_LOGIT_BOUND)) - self.right_logit) * weight / n
        self.samples = min(self.samples + weight, self.memory)

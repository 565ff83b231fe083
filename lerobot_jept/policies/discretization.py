"""Action discretisation shared by the builders (executed actions) and the policy (targets and outputs).

The paper (Appendix B) splits every action dimension into ``num_bins`` (7) evenly spaced bins over the
action range; an expert's continuous action is replaced by the nearest bin centre before it is executed, and
the policy predicts a class per dimension whose bin centre is then executed.
"""

import numpy as np


def bin_centres(num_bins: int, low=-1.0, high=1.0) -> np.ndarray:
    """Evenly spaced bin centres from ``low`` to ``high`` inclusive: (num_bins,) for one range, (A, num_bins)
    for per-dimension ranges (``low`` and ``high`` of shape (A,))."""
    if num_bins < 2:
        raise ValueError(f"num_bins must be at least 2, got {num_bins}.")
    return np.linspace(
        np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64), num_bins, axis=-1
    )


def to_bin_indices(action: np.ndarray, num_bins: int, low: float = -1.0, high: float = 1.0) -> np.ndarray:
    """Index of the nearest bin centre for every element of ``action`` (values outside are clipped)."""
    scaled = (np.clip(action, low, high) - low) / (high - low) * (num_bins - 1)
    return np.rint(scaled).astype(np.int64)


def snap_to_bins(action: np.ndarray, num_bins: int, low: float = -1.0, high: float = 1.0) -> np.ndarray:
    """Replace every element of ``action`` by its nearest bin centre (float32)."""
    return bin_centres(num_bins, low, high)[to_bin_indices(action, num_bins, low, high)].astype(np.float32)

"""Hypothesis strategies for masses, shared by the tests."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

# Masses at the corners and edges of the simplex, where formulas divide by small numbers.
EDGE_MASSES = [
    (1.0, 0.0, 0.0),
    (0.0, 1.0, 0.0),
    (0.0, 0.0, 1.0),
    (0.5, 0.5, 0.0),
    (0.5, 0.0, 0.5),
    (0.0, 0.5, 0.5),
    (1e-7, 0.0, 1.0 - 1e-7),
]


@st.composite
def masses(draw: st.DrawFn, edges: bool = True) -> np.ndarray:
    """One mass [m_f, m_o, m_u] as float32, on the simplex, edge cases included."""
    if edges and draw(st.integers(0, 4)) == 0:
        return np.array(draw(st.sampled_from(EDGE_MASSES)), dtype=np.float32)
    w = [draw(st.floats(0.0, 1.0)) for _ in range(3)]
    s = sum(w)
    if s <= 1e-6:
        return np.array([0.0, 0.0, 1.0], dtype=np.float32)
    m = np.array([w[0] / s, w[1] / s, 0.0])
    m[2] = max(0.0, 1.0 - m[0] - m[1])
    return m.astype(np.float32)


def random_masses(
    rng: np.random.Generator, shape: tuple[int, ...], p_edge: float = 0.1
) -> np.ndarray:
    """A float32 mass grid of ``shape + (3,)``, a fraction ``p_edge`` of cells at simplex
    corners/edges."""
    m = rng.dirichlet([1.0, 1.0, 1.0], size=shape).astype(np.float32)
    edge = rng.random(shape) < p_edge
    picks = np.array(EDGE_MASSES, dtype=np.float32)[rng.integers(0, len(EDGE_MASSES), size=shape)]
    m[edge] = picks[edge]
    return m

"""What this installation of evgrid is: its version, the source checkout it runs from, and how
to install an extra there. The ground floor: imports nothing of evgrid.
"""

from __future__ import annotations

__all__ = [
    "SHIPPED_CHECKPOINTS",
    "__version__",
    "install_hint",
    "shipped_checkpoint",
    "source_checkout",
]

__version__ = "0.2.0"

#: Ev-Net checkpoints shipped inside the package (``evgrid/ism/checkpoints/``), by the name a
#: config or option may give instead of a path (docs/training.md#the-shipped-checkpoints):
#: ``shipped`` is the default deep IRM (``sim-v2``: accumulated lidar targets and the paper+cor
#: loss); the others are loadable by their names (``sim-v1``: the paper's single-frame targets).
SHIPPED_CHECKPOINTS: dict[str, str] = {
    "shipped": "evnet_sim_v2.safetensors",
    "sim-v1": "evnet_sim.safetensors",
    "sim-v2": "evnet_sim_v2.safetensors",
}


def shipped_checkpoint(name: object):
    """The file of the shipped checkpoint ``name`` (a key of :data:`SHIPPED_CHECKPOINTS`), else
    None (``name`` is a path, or no name)."""
    from pathlib import Path

    if not isinstance(name, str) or name not in SHIPPED_CHECKPOINTS:
        return None
    return Path(__file__).resolve().parent / "ism" / "checkpoints" / SHIPPED_CHECKPOINTS[name]


def install_hint(extra: str) -> str:
    """The command that installs ``extra`` where this evgrid runs from: ``pip install -e
    '<checkout>[extra]'`` from a source checkout (the README's way), ``pip install
    'evgrid[extra]'`` from an installed wheel. Every install hint in evgrid comes from here."""
    root = source_checkout()
    if root is None:
        return f"pip install 'evgrid[{extra}]'"
    import os
    from pathlib import Path

    cwd = Path.cwd().resolve()
    if cwd == root:
        here = "."
    elif cwd in root.parents:  # the checkout below us: short and still right from here
        here = os.path.relpath(root, cwd)
    else:  # elsewhere an absolute path reads better than a climb of ../
        here = str(root)
    return f"pip install -e '{here}[{extra}]'"


def source_checkout():
    """The root of the source checkout evgrid is imported from (``<root>/src/evgrid`` with a
    ``pyproject.toml`` naming evgrid beside ``src``: an editable install or ``PYTHONPATH=src``),
    else None (an installed wheel, whose site-packages has no such file)."""
    import tomllib
    from pathlib import Path

    pkg = Path(__file__).resolve().parent
    if pkg.parent.name != "src":
        return None
    root = pkg.parent.parent
    try:
        with open(root / "pyproject.toml", "rb") as f:
            name = tomllib.load(f).get("project", {}).get("name")
    except (OSError, tomllib.TOMLDecodeError):
        return None
    return root if name == "evgrid" else None

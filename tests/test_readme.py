"""Every Python block of the README and of the API tour (docs/api.md) runs as written."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = {"readme": ROOT / "README.md", "api": ROOT / "docs" / "api.md"}
BLOCKS = {
    f"{page}-block{i}": code
    for page, path in PAGES.items()
    for i, code in enumerate(re.findall(r"```python\n(.*?)```", path.read_text(), re.S))
}


def test_every_page_has_python_blocks():
    for page in PAGES:
        assert any(k.startswith(f"{page}-") for k in BLOCKS), f"no python block in {PAGES[page]}"


@pytest.mark.parametrize("code", list(BLOCKS.values()), ids=list(BLOCKS))
def test_readme_python_block_runs(code, tmp_path):
    if code.startswith("# requires: nuScenes"):
        pytest.skip("needs the nuScenes dataset on disk")
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr

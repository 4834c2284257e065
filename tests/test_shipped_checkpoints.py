"""Shipped Ev-Net checkpoints by name (evgrid.package.SHIPPED_CHECKPOINTS)."""

import json

import pytest

from evgrid.config import RunConfig, load_config
from evgrid.ism.deep import checkpoint_file, default_checkpoint
from evgrid.ism.evnet import load_checkpoint
from evgrid.learn.train import CHECKPOINT_NAMES, checkpoint_path
from evgrid.package import SHIPPED_CHECKPOINTS, shipped_checkpoint


@pytest.mark.parametrize("name", sorted(SHIPPED_CHECKPOINTS))
def test_every_name_is_a_loadable_file(name):
    path = checkpoint_file(name)
    assert path.is_file(), path
    assert load_checkpoint(path).model.config.in_channels > 0
    assert checkpoint_path(name) == str(path)
    assert name in CHECKPOINT_NAMES


def test_default_is_the_one_named_shipped_and_paths_stay_paths(tmp_path):
    assert checkpoint_file(None) == default_checkpoint() == shipped_checkpoint("shipped")
    assert str(checkpoint_file(tmp_path / "x.safetensors")) == str(tmp_path / "x.safetensors")
    assert shipped_checkpoint("no-such-name") is None
    assert shipped_checkpoint(None) is None


def test_a_config_file_keeps_a_name_and_makes_a_path_absolute(tmp_path):
    from evgrid.config import document

    d = document(RunConfig())
    d["mapper"]["checkpoint"] = "sim-v1"
    (tmp_path / "a.json").write_text(json.dumps(d))
    assert load_config(tmp_path / "a.json").mapper.checkpoint == "sim-v1"
    d["mapper"]["checkpoint"] = "ck/evnet.safetensors"
    (tmp_path / "b.json").write_text(json.dumps(d))
    assert load_config(tmp_path / "b.json").mapper.checkpoint == str(
        tmp_path / "ck" / "evnet.safetensors"
    )


def test_a_name_given_with_set_stays_a_name(tmp_path, monkeypatch):
    from evgrid.config import resolve_config

    monkeypatch.chdir(tmp_path)
    for name in SHIPPED_CHECKPOINTS:
        config = resolve_config(RunConfig, overrides=[("mapper.checkpoint", name)])
        assert config.mapper.checkpoint == name
    config = resolve_config(RunConfig, overrides=[("mapper.checkpoint", "mine.safetensors")])
    assert config.mapper.checkpoint == str(tmp_path / "mine.safetensors")

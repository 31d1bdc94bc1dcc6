"""experiments/phase1_study.py: every variant builds a configuration that can train, and the
cpu preset adopts only measured variants."""

from __future__ import annotations

from pathlib import Path

import pytest
from experiment_scripts import load_experiment


@pytest.fixture
def study(tmp_path, monkeypatch):
    """The script as a module, with $NMJAX_DATA on a 3-sequence synth-arm set; bigger sets are
    recorded, not generated."""
    from nmjax.data import synthetic

    synthetic.generate(
        "synth-arm", tmp_path / "synth-arm", num_sequences=3, frames=12, points=1500, progress=False
    )
    monkeypatch.setenv("NMJAX_DATA", str(tmp_path))
    module = load_experiment("phase1_study.py")
    generated = []
    real = synthetic.ensure_dataset

    def ensure(name, root=None, **options):
        if options:
            generated.append((name, Path(root).name, options))
            return Path(root)
        return real(name, root)

    monkeypatch.setattr(module.synthetic, "ensure_dataset", ensure)
    module.generated = generated
    return module


def test_every_variant_is_a_valid_config_with_its_change(study):
    from nmjax.train import skel

    base = study.variant_config("synth-arm", "base", 12.0, 3)
    assert base.seed == 3 and base.data.seed == 3 and base.time_limit_minutes == 12.0
    for name in study.VARIANTS:
        cfg = study.variant_config("synth-arm", name, 12.0, 0, steps=50)
        skel.check_config(cfg)
        assert cfg.steps == 50 and cfg.time_limit_minutes == 0.0, name
    assert study.variant_config("synth-arm", "sigma_paper", 1, 0).model.sigma_g == 0.75
    gt = study.variant_config("synth-arm", "gt_stride2", 1, 0)
    assert gt.model.num_keypoints == 13 and gt.weights.vol_target == "joints"  # K = J
    assert gt.model.heatmap_stride == 2
    big = study.variant_config("synth-arm", "data10x_vol10", 1, 0)
    assert Path(big.data.root).name == "synth-arm-n300-seed1" and big.weights.vol == 10.0
    assert ("synth-arm", "synth-arm-n300-seed1", {"num_sequences": 300, "seed": 1}) in (
        study.generated
    )
    with pytest.raises(SystemExit, match="unknown variant"):
        study.variant_config("synth-arm", "nope", 1, 0)


def test_base_variant_is_the_cpu_preset_counted_in_steps(study):
    import dataclasses

    from nmjax.config import skel_preset, with_steps

    base = study.variant_config("synth-hand", "base", 12.0, 0)
    preset = skel_preset("synth-hand", "cpu")
    assert base == dataclasses.replace(with_steps(preset, 100_000), time_limit_minutes=12.0, seed=0)
    assert base.epochs == 0 and (base.weights.vol, base.model.keypoint_temperature) == (0.1, 1.0)
    fixed = study.variant_config("synth-arm", "vol10_temp0.5", 0.0, 1, steps=600)
    assert (fixed.steps, fixed.time_limit_minutes, fixed.seed) == (600, 0.0, 1)
    assert (fixed.weights.vol, fixed.model.keypoint_temperature) == (10.0, 0.5)

"""The two run configurations of the released run, from its options (opt.pickle).

`configs_from_options` refuses options that select a network nmjax does not implement
(`SUPPORTED_OPTIONS`) and takes the rest from the dataset's nmjax presets.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from nmjax.release.layout import Widths

# Options that select a network other than the one nmjax implements: {name: the supported value}.
SUPPORTED_OPTIONS = {
    "dyna_module": "HSVRNNBVH",  # rotations + forward kinematics ("nm")
    "transition_type": "dl",
    "keypoints_graph": "affinity_params",
    "affinity_ver": 3,  # softmax over the K - 1 others (Eq. 12)
    "const_intensity": 3,  # the spatio-temporal heatmap of the temporal mean (Eq. 6)
    "input_dim": 3,
    "fixed_sigma": 1,
    "gaussian_cat_type": "none",
    "is_binarized": 1,  # occupancy voxels
}
GRAPH_LOSS_VERSIONS = {0: True, 1: False}  # graph_loss_ver -> LossWeights.intensity_weighted
POSTERIOR_SAMPLES = 10  # the release's SAMPLE_NUM, best of S in training and generation


def _option(options: Mapping[str, Any], name: str) -> Any:
    if name not in options:
        raise ValueError(
            f"the options lack {name!r}; give the opt.pickle saved with the checkpoint"
        )
    return options[name]


def configs_from_options(options: Mapping[str, Any], widths: Widths, run: str | Path) -> tuple:
    """(SkelTrainConfig, DynTrainConfig) of the released run, for run folders under `run`.

    From the options: the dataset (its nmjax preset supplies the phase-1 crop length and epochs,
    as the release's dataset/config.py does), grid G, K, sigma_g, the N affinities, the sample
    rate, the phase-1 loss weights (complexity = the release's sparsity_const_weight, the term
    its code calls the paper's complexity loss), D_z, D_h, the phase-2 crop T = Ttot, batch,
    epochs, learning rate, KL weight and seed (the phase-2 preset supplies the rest of the
    release's recipe: Adam restarted every epoch, no clipping).

    Raises:
      ValueError: an option that selects a network nmjax does not implement, a missing option,
        or a dataset nmjax does not know.
    """
    from nmjax.config import DynamicsConfig, dataset_spec, dyn_preset, skel_preset
    from nmjax.config_io import replace_fields

    for name, value in SUPPORTED_OPTIONS.items():
        if _option(options, name) != value:
            raise ValueError(
                f"the options set {name}={options[name]!r}; nmjax implements the released "
                f"network with {name}={value!r} (pretrained/aist/opt.pickle)"
            )
    version = _option(options, "graph_loss_ver")
    if version not in GRAPH_LOSS_VERSIONS:
        raise ValueError(f"the options set graph_loss_ver={version!r}; nmjax has versions 0 and 1")
    dataset = str(_option(options, "dataset"))
    dataset_spec(dataset)
    run = Path(run)
    skel = skel_preset(dataset, "default")
    grid = int(_option(options, "grid_size"))
    data = dataclasses.replace(
        skel.data, grid=grid, sample_rate=int(_option(options, "sample_rate"))
    )
    model = dataclasses.replace(
        skel.model,
        grid=grid,
        num_keypoints=int(_option(options, "nkeypoints")),
        channels=widths.channels,
        hourglass_channels=widths.hourglass,
        sigma_g=float(_option(options, "gaussian_sigma")),
        num_affinity=int(_option(options, "nneighbor")),
    )
    weights = dataclasses.replace(
        skel.weights,
        recon=float(_option(options, "recon_weight")),
        sparse=float(_option(options, "sparse_weight")),
        sep=float(_option(options, "sep_weight")),
        vol=float(_option(options, "vol_reg_weight")),
        local=float(_option(options, "local_const_weight")),
        time=float(_option(options, "time_const_weight")),
        complex=float(_option(options, "sparsity_const_weight")),
        traj=float(_option(options, "graph_traj_weight")),
        sep_sigma=float(_option(options, "sep_sigma")),
        intensity_weighted=GRAPH_LOSS_VERSIONS[version],
    )
    seed = int(_option(options, "seed"))
    learning_rate = float(_option(options, "lrate"))
    skel = replace_fields(
        skel,
        data=data,
        model=model,
        weights=weights,
        learning_rate=learning_rate,
        seed=seed,
        run=str(run / "skel"),
    )
    dyn = dyn_preset(dataset, "default")
    dyn = replace_fields(
        dyn,
        skel_run=str(run / "skel"),
        model=DynamicsConfig(
            model="nm",
            latent=int(_option(options, "nlatent_kypt")),
            hidden=int(_option(options, "nhidden_kypt")),
            mlp=widths.mlp,
            posterior_samples=POSTERIOR_SAMPLES,
        ),
        data=dataclasses.replace(
            dyn.data,
            frames=int(_option(options, "Ttot")),
            batch_size=int(_option(options, "nbatch")),
        ),
        epochs=int(_option(options, "nepoch")),
        learning_rate=learning_rate,
        # its clip_grad_norm_ runs on gradients already applied (docs/architecture.md §6b)
        clip_norm=0.0,
        kl_weight=float(_option(options, "kl_kypt_weight")),
        seed=seed,
        run=str(run / "dyn"),
    )
    return skel, dyn

"""Keypoint detector of the skeleton module (paper Sec. 4, Fig. 8-9; docs/architecture.md §6).

voxels v_{1:T} -> per-frame features c_t (f_feat) -> heatmaps (f_heat, fused with the
spatio-temporal heatmaps of the temporal mean, Eq. 6) -> keypoints x_t = (mu, alpha) ->
gaussian maps g_t -> reconstruction v_hat_t = f_dec(g_t, c_1, g_1) relative to v_1 (Eq. 7).
The N affinity matrices (Eq. 12) are free parameters of the same module.
Frames are folded into the batch axis; nothing loops over time or keypoints.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from flax import nnx

from nmjax import keypoints as kp_lib
from nmjax.config import DetectorConfig
from nmjax.models.blocks import (
    DEFAULT_EVALUATION,
    INIT_STD,
    LEAK,
    Conv3D,
    ConvNormAct,
    FeatureNet,
    check_heatmap_stride,
    normal_init,
)
from nmjax.models.conv_kernels import Evaluation, in_compute_dtype

# The detector's initial weights (`DetectorConfig.init`).
DETECTOR_INITS = ("release", "fan_in")


def check_detector_config(cfg: DetectorConfig) -> None:
    """Raises ValueError naming the field when `cfg` cannot build a working detector."""
    if cfg.num_keypoints < 2:
        raise ValueError(
            f"model.num_keypoints (K) must be >= 2 for an affinity between keypoints, got "
            f"{cfg.num_keypoints}"
        )
    check_heatmap_stride(cfg.heatmap_stride)
    if cfg.grid < 4 or cfg.grid % 4:
        raise ValueError(
            f"model.grid (G) must be a positive multiple of 4 (heatmaps live on G/"
            f"{cfg.heatmap_stride}, the hourglass below them), got {cfg.grid}"
        )
    if cfg.channels < 4:
        raise ValueError(f"model.channels (C) must be >= 4 (C/4 stem channels), got {cfg.channels}")
    if cfg.num_affinity < 1:
        raise ValueError(f"model.num_affinity (N) must be >= 1, got {cfg.num_affinity}")
    if cfg.sigma_g <= 0:
        raise ValueError(f"model.sigma_g must be positive, got {cfg.sigma_g}")
    if not cfg.keypoint_temperature > 0:
        raise ValueError(
            f"model.keypoint_temperature must be positive, got {cfg.keypoint_temperature}"
        )
    Evaluation(cfg.conv_form, cfg.compute_dtype)  # refuses an unknown form or dtype
    if cfg.init not in DETECTOR_INITS:
        raise ValueError(f"model.init must be one of {', '.join(DETECTOR_INITS)}, got {cfg.init!r}")


class VoxelDecoder(nnx.Module):
    """f_dec of Fig. 9: [g_t, c_1, g_1, coords] at g^3 -> raw occupancy logits at G^3.

    Two stages (C -> C/2 -> C/4) of two conv3-GN-LeakyReLU blocks; the first block of a stage
    upsamples its input 2x (trilinear) before its convolution: in both stages when G / g = 4, in
    the second only when G / g = 2.
    """

    def __init__(
        self,
        in_ch: int,
        channels: int,
        stride: int = 4,
        *,
        evaluation: Evaluation = DEFAULT_EVALUATION,
        rngs: nnx.Rngs,
    ):
        check_heatmap_stride(stride)
        c2, c4 = max(1, channels // 2), max(1, channels // 4)
        self.upsample_first = stride == 4
        kw = {"evaluation": evaluation, "rngs": rngs}
        self.inp = Conv3D(in_ch, channels, 1, **kw)
        self.up1 = nnx.Sequential(
            ConvNormAct(channels, c2, 3, upsample=self.upsample_first, **kw),
            ConvNormAct(c2, c2, 3, **kw),
        )
        self.up2 = nnx.Sequential(
            ConvNormAct(c2, c4, 3, upsample=True, **kw), ConvNormAct(c4, c4, 3, **kw)
        )
        self.out = Conv3D(c4, 1, 1, **kw)

    def input_features(self, maps: jax.Array, context: jax.Array) -> jax.Array:
        """The input 1x1x1 conv + LeakyReLU on [g_t, context] of every frame.

        The conv is linear: its share of the frame-independent channels (the context) is computed
        once per crop and broadcast over time instead of concatenated to every frame.

        Args:
          maps: (B, T, g, g, g, K) gaussian maps g_t of each frame.
          context: (B, g, g, g, C + K + 3) [c_1, g_1, coords], the same for all frames of a crop.

        Returns:
          (B, T, g, g, g, C) float32.
        """
        k = maps.shape[-1]
        w = self.inp.kernel[...][0, 0, 0]  # (K + C + K + 3, C), rows in input-channel order
        maps, context, w = in_compute_dtype(self.inp.evaluation.dtype, maps, context, w)
        shared = (context @ w[k:]).astype(jnp.float32) + self.inp.bias[...]  # (B, g, g, g, C)
        return nnx.leaky_relu((maps @ w[:k]).astype(jnp.float32) + shared[:, None], LEAK)

    def __call__(self, maps: jax.Array, context: jax.Array) -> jax.Array:
        """Raw logits (B, T, G, G, G) of every frame; the arguments are `input_features`'."""
        b, t = maps.shape[:2]
        x = self.input_features(maps, context)
        x = self.up2(self.up1(x.reshape(b * t, *x.shape[2:])))
        raw = self.out(x)[..., 0]
        return raw.reshape(b, t, *raw.shape[1:])


class KeypointDetector(nnx.Module):
    """The phase-1 network: keypoints, reconstruction and affinity parameters.

    Attributes:
      features: f_feat on single frames (C channels).
      st_features: the same network with 2C channels on the temporal mean (Eq. 6).
      heat, st_heat: 1x1x1 heatmap heads (-> K), LeakyReLU (as released: their outputs can be
        negative).
      fuse: 1x1x1 conv (2 -> 1) shared by all keypoints, fusing frame and spatio-temporal heatmaps,
        then softplus: the only positive-valued layer of the heatmap path.
      decoder: f_dec.
      affinity_params: (N, K, K-1) initialised to ones (Eq. 12).
    """

    def __init__(self, cfg: DetectorConfig, *, rngs: nnx.Rngs):
        check_detector_config(cfg)
        self.cfg = cfg
        k, c = cfg.num_keypoints, cfg.channels
        hg = tuple(cfg.hourglass_channels)
        stride = cfg.heatmap_stride
        kw = {"evaluation": Evaluation(cfg.conv_form, cfg.compute_dtype), "rngs": rngs}
        self.features = FeatureNet(c, hg, cfg.grid, stride, **kw)
        self.st_features = FeatureNet(2 * c, hg, cfg.grid, stride, **kw)
        self.heat = Conv3D(c, k, 1, **kw)
        self.st_heat = Conv3D(2 * c, k, 1, **kw)
        # A 1x1x1 conv over the 2 stacked heatmaps; weights N(0, INIT_STD^2), bias 0 as released.
        self.fuse = nnx.Linear(
            2,
            1,
            kernel_init=nnx.initializers.normal(INIT_STD),
            bias_init=nnx.initializers.zeros,
            rngs=rngs,
        )
        self.decoder = VoxelDecoder(2 * k + c + 3, c, stride, **kw)
        self.affinity_params = nnx.Param(jnp.ones((cfg.num_affinity, k, k - 1), jnp.float32))
        if cfg.init == "fan_in":
            self.init_fan_in(rngs)

    def init_fan_in(self, rngs: nnx.Rngs) -> None:
        """Redraws every convolution kernel N(0, 1 / fan_in) and starts the fusion at
        1 x frame heatmap + 0 x spatio-temporal heatmap - 4 (`DetectorConfig.init = "fan_in"`)."""
        for _, module in nnx.iter_modules(self):
            if isinstance(module, Conv3D):
                shape = module.kernel[...].shape
                fan_in = math.prod(shape[:-1])
                module.kernel[...] = normal_init(rngs.params(), shape, 1.0 / math.sqrt(fan_in))
        self.fuse.kernel[...] = jnp.asarray([[1.0], [0.0]], jnp.float32)
        self.fuse.bias[...] = jnp.asarray([-4.0], jnp.float32)

    def affinity(self) -> jax.Array:
        """(N, K, K) row-softmaxed affinity with zero diagonal (Eq. 12)."""
        return kp_lib.affinity_from_params(self.affinity_params[...])

    def detect(self, voxels: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Heatmaps and keypoints of every frame.

        Args:
          voxels: (B, T, G, G, G) occupancy in [0, 1].

        Returns:
          heatmaps (B, T, g, g, g, K), keypoints (B, T, K, 4), features (B, T, g, g, g, C).
        """
        b, t = voxels.shape[:2]
        feats = self.features(voxels.reshape(b * t, *voxels.shape[2:]))  # (B*T, g, g, g, C)
        heat = nnx.leaky_relu(self.heat(feats), LEAK)  # (B*T, g, g, g, K)
        mean = jnp.mean(voxels, axis=1)  # (B, G, G, G): the temporal mean of Eq. 6
        st_heat = nnx.leaky_relu(self.st_heat(self.st_features(mean)), LEAK)  # (B, g, g, g, K)
        heat = heat.reshape(b, t, *heat.shape[1:])
        st_heat = jnp.broadcast_to(st_heat[:, None], heat.shape)
        stacked = jnp.stack([heat, st_heat], axis=-1)  # (B, T, g, g, g, K, 2)
        heatmaps = jax.nn.softplus(self.fuse(stacked)[..., 0])
        keypoints = kp_lib.heatmap_to_keypoints(heatmaps, self.cfg.keypoint_temperature)
        return heatmaps, keypoints, feats.reshape(b, t, *feats.shape[1:])

    def decode(self, keypoints: jax.Array, first_features: jax.Array, first_voxels: jax.Array):
        """Eq. 7: reconstruction of every frame from its keypoints and the first frame.

        Args:
          keypoints: (B, T, K, 4).
          first_features: (B, g, g, g, C) features c_1 of frame 1.
          first_voxels: (B, G, G, G) v_1.

        Returns:
          (B, T, G, G, G) probabilities sigmoid(s (tanh(raw) + v_1 - 0.5)).
        """
        g = first_features.shape[1]
        maps = kp_lib.gaussian_maps(keypoints, self.cfg.sigma_g, g)  # (B, T, g, g, g, K)
        context = kp_lib.add_coord_channels(jnp.concatenate([first_features, maps[:, 0]], axis=-1))
        raw = self.decoder(maps, context)  # (B, T, G, G, G)
        sharp = self.cfg.decoder_sharpness
        return jax.nn.sigmoid(sharp * (jnp.tanh(raw) + first_voxels[:, None] - 0.5))

    def __call__(self, voxels: jax.Array) -> dict[str, jax.Array]:
        """Runs the detector on a batch of crops.

        Args:
          voxels: (B, T, G, G, G) float32 occupancy.

        Returns:
          dict with "recon" (B,T,G,G,G) probabilities, "heatmaps" (B,T,g,g,g,K), "keypoints"
          (B,T,K,4) and "affinity" (N,K,K): with the batch ("voxels", "joints"), the inputs of
          `nmjax.losses.skeleton_loss`.
        """
        g = self.cfg.grid
        if voxels.ndim != 5 or voxels.shape[2:] != (g, g, g):
            raise ValueError(
                f"KeypointDetector: expected voxels (B, T, {g}, {g}, {g}), got {voxels.shape}"
            )
        heatmaps, keypoints, feats = self.detect(voxels)
        recon = self.decode(keypoints, feats[:, 0], voxels[:, 0])
        return {
            "recon": recon,
            "heatmaps": heatmaps,
            "keypoints": keypoints,
            "affinity": self.affinity(),
        }

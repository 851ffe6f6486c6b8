"""Reference models of the benchmark: DSR-Net and the paper's baselines (torch, numpy only).

`ModelConfig` selects the variant (one switch each, one network): `dsr` (warped history),
`single` (no history), `nowarp` (history not warped), `gtwarp` (history warped with ground-truth
flow: an oracle) and `3dflow` (per-voxel flow from a conv decoder, no history).
"""

from dsr_bench.models.config import MODEL_NAMES, ModelConfig
from dsr_bench.models.dsr_net import DSRNet

__all__ = ["MODEL_NAMES", "DSRNet", "ModelConfig"]

"""Reference models of the benchmark: DSR-Net and the paper's baselines (torch, numpy only).

`ModelConfig` selects the variant (one switch each, one network): `dsr` (warped history),
`single` (no history), `nowarp` (history not warped), `gtwarp` (history warped with ground-truth
flow: an oracle) and `3dflow` (per-voxel flow from a conv decoder, no history).

Submodules that need torch (`dsr_net`, `data`, `training`, ...) are imported on use, so that
`dsr_bench.models.predictors` (the oracle and static references) imports with numpy alone.
"""

from dsr_bench.models.config import MODEL_NAMES, ModelConfig

# DSRNet comes from __getattr__ below (torch imported on use), which ruff cannot see.
__all__ = ["MODEL_NAMES", "DSRNet", "ModelConfig"]  # noqa: F822


def __getattr__(name: str):
    if name == "DSRNet":
        from dsr_bench.models.dsr_net import DSRNet

        return DSRNet
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

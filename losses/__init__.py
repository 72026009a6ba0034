"""Losses and metrics for unsupervised event-based optical flow (docs/method.md, "Losses" and "Metrics").

Pure functions of tensors: no state, no I/O, nothing else of the project imported.
Flow is (B, 2, H, W) in pixels of displacement over the window at full sensor resolution;
events come as a padded :class:`EventBatch`.
"""

from .average_timestamp import average_timestamp_loss
from .contrast import CMAX_WEIGHTS, contrast_maximisation_flow
from .event_count import event_count_loss
from .events import EventBatch
from .finish import unrolled_finish
from .hmc import (
    AT_NORMALISATIONS,
    REFERENCE_TIMES,
    UPSAMPLINGS,
    LossOutput,
    accumulated_hmc_loss,
    at_loss,
    border_rule_weight,
    hmc_loss,
    rebase_to_events,
    to_full_resolution,
)
from .image_terms import event_image_terms
from .iwe import average_timestamp_images, warped_corners, warped_event_images
from .kernel_switch import cpu_kernels, cpu_kernels_enabled, set_cpu_kernels
from .metrics import (
    dense_flow_error,
    dense_flow_error_torch,
    flow_error,
    flow_error_torch,
    fwl,
    fwl_torch,
    rsat,
    rsat_torch,
)
from .sampling import sample_flow
from .smoothness import charbonnier_smoothness, event_pixel_mask
from .spec import BORDER_RAMP, LOSS_NAMES, LossSpec, LossWeights, border_weight, check_border_ramp
from .splat import bilinear_splat, crop_padding, padded_corners, splat_rows
from .terms import TERMS, Term, TermInputs
from .warp import forward_warp_flow, warp_events
from .window import accumulated_window_loss, window_loss, zero_flow_loss

__all__ = [
    "contrast_maximisation_flow",
    "CMAX_WEIGHTS",
    "cpu_kernels",
    "cpu_kernels_enabled",
    "set_cpu_kernels",
    "EventBatch",
    "LossOutput",
    "LossSpec",
    "LossWeights",
    "window_loss",
    "zero_flow_loss",
    "accumulated_window_loss",
    "TERMS",
    "Term",
    "TermInputs",
    "border_weight",
    "unrolled_finish",
    "LOSS_NAMES",
    "border_rule_weight",
    "hmc_loss",
    "at_loss",
    "accumulated_hmc_loss",
    "to_full_resolution",
    "rebase_to_events",
    "UPSAMPLINGS",
    "REFERENCE_TIMES",
    "AT_NORMALISATIONS",
    "BORDER_RAMP",
    "check_border_ramp",
    "sample_flow",
    "warp_events",
    "forward_warp_flow",
    "bilinear_splat",
    "padded_corners",
    "splat_rows",
    "crop_padding",
    "event_image_terms",
    "warped_event_images",
    "warped_corners",
    "average_timestamp_images",
    "average_timestamp_loss",
    "event_count_loss",
    "charbonnier_smoothness",
    "event_pixel_mask",
    "dense_flow_error",
    "dense_flow_error_torch",
    "flow_error",
    "flow_error_torch",
    "fwl",
    "fwl_torch",
    "rsat",
    "rsat_torch",
]

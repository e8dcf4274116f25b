"""Exceptions of the perception pipeline: each names the step that could not give an answer."""

from __future__ import annotations


class PerceptionError(ValueError):
    """Bad input, or a result the pipeline cannot vouch for."""


class PointCloudError(PerceptionError):
    """A depth image or point array that cannot be turned into points."""


class SegmentationError(PerceptionError):
    """No table plane, or no object cluster, in the cloud."""


class RegistrationError(PerceptionError):
    """The model could not be registered within the fitness and RMSE thresholds."""


class DepthMapError(PerceptionError):
    """A contact depth-map without a right answer (empty patch, degenerate crop or bins)."""


class OutOfReachError(DepthMapError):
    """No model point in a gel's contact volume: the gel does not reach the object."""


class ImageComparisonError(PerceptionError):
    """Images that SSIM or PSNR cannot compare: dtype, shape, size or levels outside 0..255."""

"""Galilean IMU preintegration on SGal(3): exact increments, covariance, bias Jacobians and
prediction with gravity and the Earth's rotation (docs/imu.md)."""
from .preintegration import (
    EARTH_RATE,
    STANDARD_GRAVITY,
    Preintegration,
    earth_rate_vector,
    gravity_vector,
    increment_tangents,
    predict,
    predict_jacobians,
    preintegrate,
    suffix_products,
    window_product,
)
from .streaming import StreamingPreintegration

__all__ = ["EARTH_RATE", "STANDARD_GRAVITY", "Preintegration", "earth_rate_vector",
           "gravity_vector", "increment_tangents", "predict", "predict_jacobians", "preintegrate",
           "StreamingPreintegration",
           "suffix_products", "window_product"]

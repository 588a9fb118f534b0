"""Galilean IMU preintegration on SGal(3): exact increments, covariance, bias Jacobians and
prediction with gravity and the Earth's rotation (docs/guide/imu.md); streaming accumulation,
the bias random walk and GTSAM conversions (docs/guide/imu_streaming.md); IMU, bias and GNSS
factors for the factor-graph engine (docs/guide/imu_factors.md)."""
from .factors import (
    BiasRandomWalkFactor,
    GnssPositionFactor,
    ImuFactor,
    implied_increment,
    imu_jacobians,
    imu_residual,
)
from .prediction import EARTH_RATE, STANDARD_GRAVITY, earth_rate_vector, gravity_vector, predict, predict_jacobians
from .preintegration import Preintegration, increment_tangents, preintegrate
from .products import suffix_products, window_product
from .streaming import StreamingPreintegration

__all__ = ["EARTH_RATE", "STANDARD_GRAVITY", "Preintegration", "earth_rate_vector",
           "gravity_vector", "increment_tangents", "predict", "predict_jacobians", "preintegrate",
           "StreamingPreintegration", "suffix_products", "window_product", "ImuFactor",
           "BiasRandomWalkFactor", "GnssPositionFactor", "implied_increment", "imu_jacobians",
           "imu_residual"]

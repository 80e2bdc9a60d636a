"""covo-gtsam: error-aware RGB-D visual odometry on GTSAM."""

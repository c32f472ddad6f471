"""gtsam factors and noise models whose uncertainty comes from learned geometry."""

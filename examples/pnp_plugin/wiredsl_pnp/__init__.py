"""An example wiredsl plug-in package: a measure (`pnp`, OpenCV's solvePnPRansac) and an effect
(`radial_corner_noise`, numpy only), registered through entry points in pyproject.toml."""

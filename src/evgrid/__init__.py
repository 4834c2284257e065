"""evgrid: evidential occupancy grid maps from lidar and radar, with deep ISMs as priors."""

__version__ = "0.1.0"

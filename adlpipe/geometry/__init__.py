"""Where things are: rigid transforms and the TF buffer, paths in time (transforms), the camera's projection and
lens (camera), the way back to a path (recovery)."""

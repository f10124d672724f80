"""Offline assessment of predicted trajectories on a lab's own recordings, with no simulated world: would the robot
reach them (robot.py), would the arm stay clear of what the camera saw (scene.py), does it do what the
demonstration did (keyposes.py). adlpipe.assess is the stage."""

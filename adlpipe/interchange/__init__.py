"""Datasets in other tools' formats: LeRobot v3 (Parquet and video) and Rerun recordings."""

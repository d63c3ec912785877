"""Inputs (bags, KITTI folders, PCD/PLY folders) and outputs (trajectories, maps)."""

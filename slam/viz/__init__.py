"""Seeing a run: bird's-eye pictures of its map (:mod:`slam.viz.birdseye`, matplotlib, no
extra dependency) and the live / recorded Rerun view (:mod:`slam.viz.rerun_view`, the
optional extra ``viz``: ``pip install 'pyslam-graph[viz]'``)."""

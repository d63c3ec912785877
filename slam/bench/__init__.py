"""What the scripts in ``benchmarks/`` share, importable by them and by the tests: peer
odometry (small_gicp, KISS-ICP), loop-closure record / replay / audit and oracle loops,
degraded inputs and the ran-away measures, and the jobs of the LeGO-LOAM table."""

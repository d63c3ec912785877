"""``slam simulate``: a LiDAR sequence (16-128 beams, or a 2D laser) into a bag or log."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from slam.cli.common import EXIT_BAD_INPUT, EXIT_OK, eprint, sim_progress


def add_parser(sub: Any) -> None:
    q = sub.add_parser("simulate", help="simulate a LiDAR sequence (16-128 beams) into a bag")
    q.add_argument(
        "scene",
        help="corridor | plaza (ideal sensor) | park (realistic sensor: calibration errors, "
        "mixed pixels, porous trees, terrain) | urban (car-speed city drive, 1.2 km, up to "
        "15 m/s, stops, junctions, streets driven both ways; realistic sensor) | street "
        "(straight 880 m at 15 m/s, a wide avenue of few features) | highway (straight 2 km "
        "motorway at 25 m/s: guard rails, open verges, overpasses, traffic) | building | "
        "building_loop (paper 001's floor under construction, 1.27 km S-route / 0.41 km "
        "loop) | rooms2d | office2d (2D laser, 360 deg, in floor plans: a CARMEN log)",
    )
    q.add_argument(
        "--sensor",
        choices=["vlp16", "hdl32", "hdl64", "os128"],
        help="vlp16 (default) | hdl32 | hdl64 (KITTI-style bag: no ring/time fields) | "
        "os128 (Ouster layout: t in ns, 48-byte points)",
    )
    q.add_argument("out", help="output folder")
    q.add_argument("--frames", type=int, help="number of scans (default: the whole path)")
    q.add_argument(
        "--format", choices=["ros1", "ros2", "mcap"], help="ros1 (default) | ros2 | mcap"
    )
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--no-pedestrians", action="store_true")
    q.set_defaults(func=cmd_simulate)


def cmd_simulate(args: argparse.Namespace) -> int:
    from slam.sim.floorplan2d import PLANS, simulate2d, write_sequence
    from slam.sim.simulate import SCENES, simulate

    if args.scene not in PLANS and args.scene not in SCENES:
        eprint(f"error: unknown scene {args.scene!r}; choose one of {sorted(SCENES)} (3D) or "
               f"{sorted(PLANS)} (2D laser)")  # fmt: skip
        return EXIT_BAD_INPUT
    if args.scene in PLANS:  # 2D laser in a floor plan: a CARMEN log + ground truth
        if args.format is not None or args.sensor is not None:
            eprint(f"error: {args.scene} is a 2D laser scene: it writes a CARMEN log "
                   "(--format and --sensor are for the 3D scenes)")  # fmt: skip
            return EXIT_BAD_INPUT
        seq = simulate2d(args.scene, frames=args.frames, seed=args.seed)
        log, gt = write_sequence(seq, Path(args.out))
        eprint(f"wrote {len(seq.stamps)} 2D laser scans to {log} and ground truth to {gt}")
        return EXIT_OK

    bar, progress = sim_progress(args.scene)

    try:
        res = simulate(
            args.scene,
            Path(args.out),
            frames=args.frames,
            fmt=args.format or "ros1",
            seed=args.seed,
            pedestrians=not args.no_pedestrians,
            sensor=args.sensor or "vlp16",
            progress=progress,
        )
    finally:
        bar.close()
    eprint(f"wrote {res.frames} scans to {res.bag} and ground truth to {res.ground_truth}")
    return EXIT_OK

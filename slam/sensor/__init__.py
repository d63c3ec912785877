"""Beam model of a spinning lidar, estimated from its data when the driver gives no ring field.

The elevation table (one angle per beam) is read once from the first scans and then assigns
every point of every later scan to a beam (``BeamModel.ring_of``). Two cues, in this order:

1. Point layout (beam by beam). Clouds converted from KITTI .bin files and organised clouds (Ouster,
   ``ring``-less Velodyne exports) store the points beam by beam: along the stored order the
   azimuth unwraps to about one turn per beam. Then the beams are the turns of the unwrapped
   azimuth, exact even where two beams' elevations overlap (HDL-64's upper block is 1/3 deg
   apart while each beam's origin sits a few cm off the sensor origin, so elevations seen from
   the origin smear by ~0.3 deg at 10 m).
2. Column order. Clouds stored column by column with every beam in every column (nuScenes
   HDL-32E: 32 points per firing, missing returns included) hold beam b at position
   i % B of every column: the ring of a point is that of its position, exact even where
   near returns smear a beam's elevation by a degree (the car's own body, nuScenes).
3. Elevation histogram. Otherwise (firing-order clouds without missing returns, shuffled
   clouds) the beams are the peaks of the histogram of elevation angles, and a point
   belongs to the nearest beam.

Ring 0 is the lowest beam (Velodyne's ``ring`` convention).

The package: ``layout`` detects beam-by-beam storage and reads rings from the point order
(its compiled kernels in ``layout_kernels``), ``beam_table`` infers the elevation table from
the first scans, ``beam_model`` holds the table and fills ring and time for every scan.
"""

from slam.sensor.beam_model import BeamModel
from slam.sensor.beam_table import beams_from_rings, column_rings, estimate_beams
from slam.sensor.layout import elevation_deg, layout_rings, layout_rings_reference, layout_seam

__all__ = [
    "BeamModel",
    "beams_from_rings",
    "column_rings",
    "elevation_deg",
    "estimate_beams",
    "layout_rings",
    "layout_rings_reference",
    "layout_seam",
]

"""Level-of-detail budgets per agent type: what a client's clipmap holds for what it follows.

A profile sets the clipmap (client/render/clipmap.py) a render client uses:
``levels`` L and ``n`` posts a side per level, the ``budget`` of terrain samples
it may take per frame (heights + 4 normals a post; thesis §3.1.4: "this sample
budget may have to be adjusted on each client"), the finest level's
spacing as a power-of-two factor of the terrain's post spacing (below 1: finer
than the DEM, where the terrain's fractal detail synthesis, terrain/detail.py,
answers if the terrain has it, else the bilinear surface), and ``pixel_error``:
a block of a level is drawn with every 2nd or 4th post inside its edges where
that moves its surface by at most this many pixels on screen
(client/render/clipmap_layer.py, ``decimated_grid``; None: every post). The view
distance follows: about half the coarsest level's extent, (n - 1) / 2 x spacing x
2^(L - 1); fog hides the edge there. ``design_fov_deg`` is the horizontal field of view
the levels are sized for (60 degrees, ``sortie render``/``sortie view``'s default; the
figures below are for it): a narrower view, a zoom, is centred towards the ground it looks at
so that the posts there are as many pixels apart as at this field of view
(client/render/clipmap_layer.py, "Narrow views").

Figures below for a 3-arc-second (about 90 m) DEM; they scale with its spacing.

| profile | L | n | budget | pixel_error | finest | coarsest | view distance | why |
|---|---|---|---|---|---|---|---|---|
| fast_jet | 6 | 255 | 3,000 | 2 px | 90 m | 2.9 km | ~365 km | at 10 km the horizon is ~360 km away; 300 m/s uncovers a finest row every 0.3 s; n = 255 keeps the screen error within 2 px on mountains, decimation cuts its triangles by more than half |
| helicopter | 6 | 127 | 1,500 | 1 px | 90 m | 2.9 km | ~180 km | low and slow: the near field matters, the horizon is nearer |
| ground_vehicle | 7 | 127 | 1,500 | 1 px | 23 m | 1.4 km | ~90 km | on the ground: detail under the wheels (fractal below the DEM), a hill's horizon |
| observer | 6 | 255 | 3,000 | 2 px | 90 m | 2.9 km | ~365 km | a fixed or slow viewpoint: more posts a level, updated rarely |

The n = 127 profiles decimate within 1 px: on the bench's Alps paths (L 7, n 127) that draws
22k triangles a frame instead of 35k at the same p99 screen error (4.25 px), median 0.167 →
0.18 px. At n = 255, 2 px draws 51k instead of 118k, p99 1.73 → 1.82 px (`sortie bench render`,
docs/BENCHMARKS.md: blocks with stitched edges, sixth session).

The budgets hold about one level's move a frame (a move uncovers two rows or columns of
n posts, x 5 samples a post; the first move of a frame is always made): a move costs about
1.3 ms of CPU here whatever its size (the calls around the samples), and at 300 m/s the
levels need a move in about one frame in twenty between them, so taking them one a frame
keeps each frame's update near one move's cost and lets a level fall behind by a frame or
two at most (`sortie bench render`: the same screen error as an unlimited budget).

The client picks the profile of the agent it follows (:func:`profile_for`): an
aircraft whose type names a helicopter gets ``helicopter``, other aircraft
``fast_jet``, ground vehicles ``ground_vehicle``, anything else ``observer``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from client.render.camera import DEFAULT_FOV_X_DEG
from sortie.errors import InvalidArgument

HELICOPTER_WORDS = ("heli", "ah64", "uh60", "uh1", "ch47", "mi24", "mi8", "bo105", "ec135")


@dataclass(frozen=True)
class LodProfile:
    name: str
    levels: int
    n: int
    budget: int
    finest_spacing_factor: float
    pixel_error: float | None = None  # blocks drawn with fewer posts within this many pixels (None: never)
    design_fov_deg: float = DEFAULT_FOV_X_DEG  # the horizontal field of view the levels are sized for

    def layer_args(self) -> dict:
        """Keyword arguments of client.render.clipmap_layer.ClipmapLayer / clipmap_factory."""
        d = asdict(self)
        d.pop("name")
        return d

    def view_distance_m(self, post_spacing_m: float) -> float:
        return (self.n - 1) / 2 * post_spacing_m * self.finest_spacing_factor * 2 ** (self.levels - 1)


PROFILES = {p.name: p for p in (
    LodProfile("fast_jet", 6, 255, 3_000, 1.0, 2.0),
    LodProfile("helicopter", 6, 127, 1_500, 1.0, 1.0),
    LodProfile("ground_vehicle", 7, 127, 1_500, 0.25, 1.0),
    LodProfile("observer", 6, 255, 3_000, 1.0, 2.0),
)}


def profile(name: str) -> LodProfile:
    if name not in PROFILES:
        raise InvalidArgument("profile", f"must be one of {', '.join(PROFILES)}", value=name)
    return PROFILES[name]


def profile_for(kind: str, type_name: str = "") -> LodProfile:
    """The profile of an agent of ``kind`` ("aircraft", "ground", "static", "observer") and type."""
    if kind == "aircraft":
        t = type_name.lower()
        if any(w in t for w in HELICOPTER_WORDS):
            return PROFILES["helicopter"]
        from fdm.catalog import is_rotorcraft  # a JSBSim model with rotors (the catalog's ah1s)

        return PROFILES["helicopter" if type_name and is_rotorcraft(type_name) else "fast_jet"]
    if kind == "ground":
        return PROFILES["ground_vehicle"]
    return PROFILES["observer"]

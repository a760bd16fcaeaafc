"""A recorded sortie as a 3-D debrief scene: glTF 2.0 (``sortie export gltf``).

Tacview replays tracks over its own terrain; a glTF scene takes the sortie into any 3-D tool
(Blender, a web viewer, Cesium) over the terrain it was flown on. One scene holds:

- **terrain**: the recorded terrain (or the one given) under the tracks' box plus a margin,
  as a textured mesh (terrain/mesh.py; land classes and light for the sortie's start time);
- **one track per entity**: a line strip through its recorded positions (ECEF, float64 in
  the recording) at the export rate, broken where the entity was absent; its node and mesh
  carry the entity's id, name, kind, type and coalition in ``extras``, coloured by coalition;
- **events** (crash, take-off, touchdown, ...) as points, listed in the scene's extras.

Everything is in one local east-north-up frame at the terrain box's centre (glTF axes: x
east, y up, z south), float32 offsets from it, so a sortie over a few hundred kilometres
keeps its tracks to the millimetre. The origin's WGS84 latitude, longitude and height are in
the scene's ``extras.sortie.frame``. The tracks' ellipsoidal heights meet the mesh's MSL
heights plus the recording's geoid undulation, as they met in the world.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path

import numpy as np

from server import recording_codec as codec
from server.acmi import check_rate, selected_ticks
from sortie.errors import InvalidArgument
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import ecef_to_geodetic, geodetic_to_ecef, radii_of_curvature
from terrain.mesh import LocalFrame, enu_to_gltf, output_format, scene_extras

DEFAULT_MARGIN_M = 2000.0  # terrain around the tracks' box
DEFAULT_LONG_SIDE = 512  # terrain vertices along the box's longer side (about 12 MB of glTF)
MAX_MARGIN_M = 200_000.0
# Track colours (RGBA) by coalition, as Tacview draws them.
COALITION_RGBA = {"blue": (40, 110, 255, 255), "red": (235, 40, 40, 255), "neutral": (230, 230, 230, 255)}


@dataclass
class Track:
    """An entity's recorded positions at the export's ticks: ``segments`` of (times (k,),
    ECEF (k, 3)) where it was present without a break."""

    entity_id: int
    segments: list = field(default_factory=list)
    _times: list = field(default_factory=list)
    _points: list = field(default_factory=list)

    def extend(self, times: np.ndarray, points: np.ndarray, present: np.ndarray, continues: bool) -> None:
        """Add the export ticks of a chunk (``present`` per tick); ``continues``: the entity
        was present at the previous export tick."""
        if not continues:
            self._close()
        breaks = np.flatnonzero(~present)
        start = 0
        for b in [*breaks.tolist(), present.size]:
            if b > start:
                self._times.append(times[start:b])
                self._points.append(points[start:b])
            if b < present.size:
                self._close()
            start = b + 1

    def _close(self) -> None:
        if self._times:
            self.segments.append((np.concatenate(self._times), np.concatenate(self._points)))
        self._times, self._points = [], []

    def finish(self) -> "Track":
        self._close()
        return self


def read_tracks(recording, rate_hz: float | None = None) -> dict[int, Track]:
    """Every entity's track at ``rate_hz`` of world time (server.acmi.selected_ticks: the
    first tick of each 1/rate interval, and the first and last ticks; None: every tick)."""
    r = recording
    steps = r.steps.vector()[codec.POS]
    tracks: dict[int, Track] = {}
    last_present: dict[int, bool] = {}
    for k in range(r.chunk_count):
        c = r.chunk(k)
        ticks = c.first_tick + np.arange(c.ticks)
        sel = np.flatnonzero(selected_ticks(ticks, r.rate_hz, rate_hz, r.first_tick, r.last_tick))
        if sel.size == 0:
            continue
        times = ticks[sel] * r.dt
        points = c.q[sel][:, :, codec.POS] * steps  # (t, e, 3) ECEF metres
        present = c.present[sel]
        held = set()
        for e, entity_id in enumerate(c.entity_ids.tolist()):
            t = tracks.setdefault(entity_id, Track(entity_id))
            t.extend(times, points[:, e], present[:, e], last_present.get(entity_id, False))
            last_present[entity_id] = bool(present[-1, e])
            held.add(entity_id)
        for entity_id in last_present.keys() - held:  # not in this chunk at all: a break
            last_present[entity_id] = False
    return {i: t.finish() for i, t in tracks.items()}


def track_box(tracks: dict, margin_m: float) -> tuple[float, float, float, float]:
    """(lat_min, lon_min, lat_max, lon_max) around every track point, plus ``margin_m`` each way.
    Longitudes are unwrapped from the first point's (a box across the antimeridian keeps
    lon_max above 180, as ``sortie terrain texture`` takes it)."""
    pts = [p for t in tracks.values() for _, p in t.segments]
    if not pts:
        raise InvalidArgument("recording", "holds no entity positions to export")
    lat, lon, _ = ecef_to_geodetic(np.concatenate(pts))
    lon = lon[0] + (lon - lon[0] + 180.0) % 360.0 - 180.0
    m, n = radii_of_curvature(float(np.clip(np.abs(lat).max(), 0.0, 89.0)))
    dlat = math.degrees(margin_m / m)
    dlon = math.degrees(margin_m / (n * math.cos(math.radians(min(float(np.abs(lat).max()) + dlat, 89.0)))))
    return (max(-90.0, float(lat.min()) - dlat), float(lon.min()) - dlon,
            min(90.0, float(lat.max()) + dlat), float(lon.max()) + dlon)


def polylines(lines: list):
    """A trimesh Path3D of polylines ((k, 3) arrays, k >= 2): glTF writes it as line segments."""
    import trimesh
    from trimesh.path.entities import Line

    starts = np.cumsum([0] + [len(a) for a in lines])
    entities = [Line(points=np.arange(a, b)) for a, b in zip(starts[:-1].tolist(), starts[1:].tolist())]
    return trimesh.path.Path3D(entities=entities, vertices=np.concatenate(lines), process=False)


def _entity_extras(info) -> dict:
    if info is None:
        return {}
    return {"entity_id": int(info.entity_id), "name": info.name, "kind": pb.EntityKind.Name(info.kind),
            "type": info.type, "coalition": info.coalition or "neutral"}


@dataclass
class GltfStats:
    path: str
    tracks: int
    track_points: int
    events: int
    terrain_vertices: int
    terrain_triangles: int
    terrain_centre_error_m_max: float | None
    bytes_written: int


def export_gltf(recording, out_path, terrain=None, *, rate_hz: float | None = None,
                margin_m: float = DEFAULT_MARGIN_M, size: str | None = None, spacing_m: float | None = None,
                texture: bool = True) -> GltfStats:
    """Write ``recording`` (server.recording.Recording) as a glTF scene to ``out_path`` (.glb or
    .gltf): tracks, events and, when ``terrain`` (anything with ``heights(lat, lon)``) is
    given, the terrain under them (``size`` / ``spacing_m`` as ``sortie terrain mesh``;
    default :data:`DEFAULT_LONG_SIDE` vertices along the longer side)."""
    import trimesh

    from terrain.mesh import build_mesh, centre_error, to_trimesh, write_scene
    from terrain.texture_cli import make_texture, sample_heights, texture_request

    if output_format(out_path) not in ("glb", "gltf"):
        raise InvalidArgument("output", "a debrief scene is written as .glb or .gltf", value=str(out_path))
    rate_hz = check_rate(rate_hz)
    if not (math.isfinite(margin_m) and 0.0 <= margin_m <= MAX_MARGIN_M):
        raise InvalidArgument("margin_m", f"must be within [0, {MAX_MARGIN_M:g}] m", value=margin_m)
    r = recording
    tracks = read_tracks(r, rate_hz)
    box = track_box(tracks, margin_m)
    frame = LocalFrame.at(0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3]), 0.0)
    undulation = float(r.header.geoid_undulation_m)
    scene = trimesh.Scene()
    extras: dict = {"recording": Path(r.path).name, "exercise": r.header.exercise_name,
                    "start_time": r.header.start_time, "world_time_s": [r.first_time_s, r.last_time_s],
                    "terrain_box": list(box), "geoid_undulation_m": undulation,
                    "heights": "ellipsoidal in the frame; terrain MSL + geoid_undulation_m"}
    stats = GltfStats(str(out_path), 0, 0, 0, 0, 0, None, 0)

    if terrain is not None:
        when = _sun_time(r, frame.lon_deg)
        req = texture_request(box, size, spacing_m, when, default_long_side=DEFAULT_LONG_SIDE)
        from terrain.mesh import MAX_VERTICES

        if req.cols * req.rows > MAX_VERTICES:
            raise InvalidArgument("size" if size else "spacing_m", f"{req.cols}x{req.rows} terrain vertices is over "
                                  f"the limit of {MAX_VERTICES:,}", value=size or spacing_m)
        sampled = sample_heights(terrain, req)
        mesh = build_mesh(*sampled, frame=frame, geoid_undulation_m=undulation)
        image = make_texture(terrain, req, sampled=sampled)[0].image if texture else None
        scene.add_geometry(to_trimesh(mesh, image, gltf_axes=True), node_name="terrain", geom_name="terrain")
        err = centre_error(mesh, terrain)
        stats.terrain_vertices, stats.terrain_triangles = mesh.vertices.shape[0], mesh.faces.shape[0]
        stats.terrain_centre_error_m_max = float(err.max()) if err.size else None
        extras["terrain"] = {"grid": [req.cols, req.rows], "sun_time_utc": when if texture else None,
                             "centre_error_m": {"rms": float(np.sqrt(np.mean(err ** 2))) if err.size else None,
                                                "max": stats.terrain_centre_error_m_max}}

    for entity_id in sorted(tracks):
        info = r.entities.get(entity_id)
        meta = _entity_extras(info)
        name = f"{info.name if info is not None and info.name else 'entity'} #{entity_id}"
        segments = [enu_to_gltf(frame.to_local(p)) for _, p in tracks[entity_id].segments]
        lines = [s for s in segments if len(s) >= 2]
        if not lines:
            continue
        path = polylines(lines)
        rgba = COALITION_RGBA.get(meta.get("coalition", "neutral"), COALITION_RGBA["neutral"])
        path.colors = np.tile(np.array(rgba, np.uint8), (len(path.entities), 1))
        times = tracks[entity_id].segments
        path.metadata.update({**meta, "world_time_s": [float(times[0][0][0]), float(times[-1][0][-1])]})
        scene.add_geometry(path, node_name=name, geom_name=name)
        stats.tracks += 1
        stats.track_points += sum(len(s) for s in lines)

    # Events where something happened to an entity (sessions joining and leaving are not placed).
    events = [ev.event for ev in r.events() if ev.event.kind not in ("join", "leave")]
    placed = [e for e in events if all(map(math.isfinite, (e.lat_deg, e.lon_deg, e.alt_msl_m)))]
    if placed:
        where = geodetic_to_ecef([e.lat_deg for e in placed], [e.lon_deg for e in placed],
                                 np.array([e.alt_msl_m for e in placed]) + undulation)
        cloud = trimesh.PointCloud(enu_to_gltf(frame.to_local(where)))
        cloud.metadata["events"] = "the events of extras.sortie.events with a position, in that order"
        scene.add_geometry(cloud, node_name="events", geom_name="events")
    extras["events"] = [{"time_s": e.time_s, "kind": e.kind, "entity_id": int(e.entity_id),
                         "lat_deg": _json_number(e.lat_deg), "lon_deg": _json_number(e.lon_deg),
                         "alt_msl_m": _json_number(e.alt_msl_m), "placed": e in placed,
                         "detail": json.loads(e.detail_json) if e.detail_json else {}} for e in events]
    stats.events = len(events)
    scene.metadata.update(scene_extras(frame, extras))
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_scene(scene, out)
    stats.bytes_written = out.stat().st_size
    return stats


def _json_number(v: float) -> float | None:
    """JSON has no NaN (RFC 8259 §6): an unknown value is null."""
    return float(v) if math.isfinite(v) else None


def _sun_time(r, lon_deg: float) -> str:
    """The sortie's start in UTC (the texture's sun), or local noon where the header has none."""
    from terrain.mesh_cli import local_noon
    from terrain.texture_cli import parse_time

    try:
        start = parse_time(r.header.start_time) + timedelta(seconds=r.first_time_s)
    except InvalidArgument:
        return local_noon(lon_deg)
    return start.replace(microsecond=0).isoformat().replace("+00:00", "Z")

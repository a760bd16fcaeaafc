"""A recorded sortie as a 3-D debrief scene: glTF 2.0 (``sortie export gltf``).

Tacview replays tracks over its own terrain; a glTF scene takes the sortie into any 3-D tool
(Blender, a web viewer, Cesium) over the terrain it was flown on. One scene holds:

- **terrain**: the recorded terrain (or the one given) under the tracks' box plus a margin,
  as a textured mesh (terrain/mesh.py; land classes and light for the sortie's start time);
- **one track per entity**: a line strip through its recorded positions (ECEF, float64 in
  the recording) at the export rate, broken where the entity was absent; its node and mesh
  carry the entity's id, name, kind, type and coalition in ``extras``, coloured by coalition;
- **the scenario's target areas**, outlined in yellow a few metres above the terrain;
- **events** (crash, take-off, touchdown, ...) as points, listed in the scene's extras;
- **one marker per entity** (a dart coloured by coalition) animated along its track: the
  scene's animation "sortie" keys its position and attitude at every exported tick (LINEAR:
  a viewer's slerp between sign-continuous quaternions) and hides it (scale 0, STEP) where
  it was absent, so any glTF viewer plays the sortie back. Animation time 0 is the first
  recorded tick (world time in the animation's extras).

trimesh writes the static scene; the markers and the animation are added to its GLB here
(buffer views, accessors, nodes, one animation: glTF 2.0 specification, "Animations"). The
files pass the Khronos glTF validator without error or warning (tests/test_gltf.py).

Everything is in one local east-north-up frame at the terrain box's centre (glTF axes: x
east, y up, z south), float32 offsets from it (within 2^-24 of the distance: a millimetre at
17 km, 8 mm at 130 km). The origin's WGS84 latitude, longitude and height are in
the scene's ``extras.sortie.frame``. The tracks' ellipsoidal heights meet the mesh's MSL
heights plus the recording's geoid undulation, as they met in the world.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import NamedTuple
from datetime import timedelta
from pathlib import Path

import numpy as np

from server import recording_codec as codec
from server.acmi import check_rate, selected_ticks
from sortie.errors import InvalidArgument
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import ecef_to_geodetic, geodetic_to_ecef, radii_of_curvature
from terrain.mesh import (ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, UNSIGNED_SHORT, LocalFrame, append_accessor,
                          enu_to_gltf, glb_bytes, gltf_bytes, output_format, read_glb, scene_extras,
                          write_atomically)

DEFAULT_MARGIN_M = 2000.0  # terrain around the tracks' box
DEFAULT_LONG_SIDE = 512  # terrain vertices along the box's longer side (about 12 MB of glTF)
MAX_MARGIN_M = 200_000.0
# Track points (each a polyline vertex twice and an animation key: about 56 bytes) one scene
# holds: 5 M is about 280 MB. A longer sortie is exported at a lower --rate.
MAX_TRACK_POINTS = 5_000_000
# Track colours (RGBA) by coalition, as Tacview draws them.
COALITION_RGBA = {"blue": (40, 110, 255, 255), "red": (235, 40, 40, 255), "neutral": (230, 230, 230, 255)}
# Target areas: outlined in yellow, TARGET_AREA_LIFT_M above the terrain, in pieces of at most
# TARGET_AREA_STEP_M so that the outline follows the ground.
TARGET_AREA_RGBA = (255, 200, 0, 255)
TARGET_AREA_LIFT_M = 5.0
TARGET_AREA_STEP_M = 50.0


class Segment(NamedTuple):
    """A stretch of an entity's track without a break: world times (k,), ECEF positions
    (k, 3) and ECEF -> body quaternions (k, 4; w, x, y, z), as recorded."""

    times: np.ndarray
    ecef: np.ndarray
    quat: np.ndarray


@dataclass
class Track:
    """An entity's recorded states at the export's ticks: ``segments`` where it was present
    without a break."""

    entity_id: int
    segments: list = field(default_factory=list)


def read_tracks(recording, rate_hz: float | None = None, skipped: list | None = None) -> dict[int, Track]:
    """Every entity's track at ``rate_hz`` of world time (server.acmi.selected_ticks: the
    first tick of each 1/rate interval, and the first and last ticks; None: every tick).
    A chunk that does not read is left out (its problem appended to ``skipped``).

    Vectorised over the recording: each chunk's present (export tick, entity) pairs are
    gathered flat, then grouped by entity (a stable sort keeps time order) and split where
    an entity's export ticks are not consecutive (it was absent, or the chunks between did
    not hold it)."""
    r = recording
    steps = r.steps.vector()
    pose = np.r_[np.arange(codec.FIELDS)[codec.POS], np.arange(codec.FIELDS)[codec.QUAT]]
    ids, slots, times, rows = [], [], [], []
    exported = 0  # export ticks before this chunk's
    for _, c in r.readable_chunks([] if skipped is None else skipped):
        ticks = c.first_tick + np.arange(c.ticks)
        sel = np.flatnonzero(selected_ticks(ticks, r.rate_hz, rate_hz, r.first_tick, r.last_tick))
        if sel.size == 0:
            continue
        t_k, e_k = np.nonzero(c.present[sel])  # row-major: time order within the chunk
        ids.append(c.entity_ids[e_k])
        slots.append(exported + t_k)
        times.append(ticks[sel][t_k] * r.dt)
        rows.append(c.q[sel[t_k], e_k][:, pose] * steps[pose])  # ECEF metres, quaternion
        exported += sel.size
    if not ids:
        return {}
    ids, slots, times, rows = (np.concatenate(a) for a in (ids, slots, times, rows))
    if ids.size == 0:
        return {}
    order = np.argsort(ids, kind="stable")
    ids, slots, times, rows = ids[order], slots[order], times[order], rows[order]
    cut = np.flatnonzero((ids[1:] != ids[:-1]) | (slots[1:] != slots[:-1] + 1)) + 1
    tracks: dict[int, Track] = {}
    for a, b in zip(np.r_[0, cut].tolist(), np.r_[cut, ids.size].tolist()):
        tracks.setdefault(int(ids[a]), Track(int(ids[a]))).segments.append(
            Segment(times[a:b], rows[a:b, :3], rows[a:b, 3:]))
    return tracks


def track_box(tracks: dict, margin_m: float) -> tuple[float, float, float, float]:
    """(lat_min, lon_min, lat_max, lon_max) around every track point, plus ``margin_m`` each way.
    Longitudes are unwrapped from the first point's (a box across the antimeridian keeps
    lon_max above 180, as ``sortie terrain texture`` takes it); a box that reaches a pole
    takes every longitude."""
    pts = [seg.ecef for t in tracks.values() for seg in t.segments]
    if not pts:
        raise InvalidArgument("recording", "holds no entity positions to export")
    lat, lon, _ = ecef_to_geodetic(np.concatenate(pts))
    lon = lon[0] + (lon - lon[0] + 180.0) % 360.0 - 180.0
    m, n = radii_of_curvature(float(np.abs(lat).max()))
    dlat = math.degrees(margin_m / m)
    lat_min, lat_max = max(-90.0, float(lat.min()) - dlat), min(90.0, float(lat.max()) + dlat)
    # The margin's longitudes at the box's most poleward latitude; a box reaching a pole, or
    # wider than half the world, takes every longitude (a polar cap).
    edge = max(abs(lat_min), abs(lat_max))
    if edge < 90.0 and float(lon.max() - lon.min()) < 180.0:
        dlon = math.degrees(margin_m / (n * math.cos(math.radians(edge))))
        if float(lon.max() - lon.min()) + 2.0 * dlon < 360.0:
            return lat_min, float(lon.min()) - dlon, lat_max, float(lon.max()) + dlon
    return lat_min, -180.0, lat_max, 180.0


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
    markers: int = 0
    target_areas: int = 0
    skipped: list = field(default_factory=list)  # the damaged chunks left out, each problem named


def check_output(out_path) -> str:
    """"glb" or "gltf", the form of a debrief scene written to ``out_path``; InvalidArgument
    naming ``output`` for any other name (terrain/mesh.py's .obj, .ply and .stl included:
    they hold no tracks, markers nor animation)."""
    if Path(out_path).suffix.lower() not in (".glb", ".gltf"):
        raise InvalidArgument("output", "a debrief scene is written as .glb or .gltf", value=str(out_path))
    return output_format(out_path)


def export_gltf(recording, out_path, terrain=None, *, rate_hz: float | None = None,
                margin_m: float = DEFAULT_MARGIN_M, size: str | None = None, spacing_m: float | None = None,
                texture: bool = True, max_error_m: float | None = None) -> GltfStats:
    """Write ``recording`` (server.recording.Recording) as a glTF scene to ``out_path`` (.glb or
    .gltf): tracks, events and, when ``terrain`` (anything with ``heights(lat, lon)``) is
    given, the terrain under them (``size`` / ``spacing_m`` as ``sortie terrain mesh``;
    default :data:`DEFAULT_LONG_SIDE` vertices along the longer side; ``max_error_m``: an
    adaptive mesh within that of every sampled post, terrain/rtin.py)."""
    import trimesh

    check_output(out_path)
    rate_hz = check_rate(rate_hz)
    if not (math.isfinite(margin_m) and 0.0 <= margin_m <= MAX_MARGIN_M):
        raise InvalidArgument("margin_m", f"must be within [0, {MAX_MARGIN_M:g}] m", value=margin_m)
    r = recording
    skipped: list = []
    tracks = read_tracks(r, rate_hz, skipped)
    points = sum(len(seg.times) for t in tracks.values() for seg in t.segments)
    if points > MAX_TRACK_POINTS:
        # At f Hz a segment of s seconds keeps at most s f + 1 ticks, and its first and last.
        segments = sum(len(t.segments) for t in tracks.values())
        present_s = points / (rate_hz or r.rate_hz)
        fits = math.floor(max(MAX_TRACK_POINTS - 3 * segments, 0) / present_s * 1000.0) / 1000.0
        raise InvalidArgument("rate", f"{points:,} track points is over the limit of {MAX_TRACK_POINTS:,}: "
                                      + (f"export at {fits:g} Hz or less" if fits > 0 else "too many entities"),
                              value=rate_hz)
    box = track_box(tracks, margin_m)
    centre_lon = 0.5 * (box[1] + box[3])  # the box's longitudes run on past +-180 across the antimeridian
    frame = LocalFrame.at(0.5 * (box[0] + box[2]), (centre_lon + 180.0) % 360.0 - 180.0 if abs(centre_lon) > 180.0
                          else centre_lon, 0.0)
    undulation = float(r.header.geoid_undulation_m)
    scene = trimesh.Scene()
    extras: dict = {"recording": Path(r.path).name, "exercise": r.header.exercise_name,
                    "start_time": r.header.start_time, "world_time_s": [r.first_time_s, r.last_time_s],
                    "terrain_box": list(box), "geoid_undulation_m": undulation,
                    "heights": "ellipsoidal in the frame; terrain MSL + geoid_undulation_m"}
    stats = GltfStats(str(out_path), 0, 0, 0, 0, 0, None, 0, skipped=skipped)

    if terrain is not None:
        _add_terrain(scene, extras, stats, r, terrain, box, frame, size, spacing_m, texture, max_error_m)
    _add_tracks(scene, stats, r, tracks, frame)
    _add_target_areas(scene, stats, r, terrain, frame)
    _add_events(scene, extras, stats, r, frame)
    scene.metadata.update(scene_extras(frame, extras))
    if scene.geometry:
        gltf, binary = read_glb(scene.export(file_type="glb"))
    else:  # no track of two points, no terrain, no placed event: the markers alone
        gltf, binary = {"asset": {"version": "2.0", "generator": "sortie"}, "scene": 0,
                        "scenes": [{"nodes": [], "extras": scene.metadata}], "nodes": []}, bytearray()
    stats.markers = add_markers(gltf, binary, tracks, r.entities, frame, r.first_time_s, r.dt)
    out = Path(out_path)
    write_atomically(out, glb_bytes(gltf, binary) if output_format(out) == "glb" else gltf_bytes(gltf, binary))
    stats.bytes_written = out.stat().st_size
    return stats


def _add_terrain(scene, extras: dict, stats: GltfStats, r, terrain, box, frame: LocalFrame, size, spacing_m,
                 texture: bool, max_error_m) -> None:
    """The terrain node: the terrain under ``box`` as a mesh (regular, or adaptive within
    ``max_error_m``), textured for the sortie's start; left out, and said so in the extras,
    where no grid cell has data."""
    from terrain.mesh import centre_error, to_trimesh
    from terrain.mesh_cli import checked_request, grid_limit, sample_mesh
    from terrain.texture_cli import texture_request

    when = _sun_time(r, frame.lon_deg)
    req = texture_request(box, size, spacing_m, when, default_long_side=DEFAULT_LONG_SIDE,
                          limit=grid_limit(max_error_m, "max_error_m"))
    req = checked_request(req, max_error_m, "max_error_m", "size" if size else "spacing_m", size or spacing_m)
    mesh, _, image = sample_mesh(terrain, req, max_error_m, frame=frame,
                                 geoid_undulation_m=float(r.header.geoid_undulation_m), texture=texture)
    if len(mesh.faces):
        scene.add_geometry(to_trimesh(mesh, image, gltf_axes=True), node_name="terrain", geom_name="terrain")
        err = centre_error(mesh, terrain)
        stats.terrain_vertices, stats.terrain_triangles = mesh.vertices.shape[0], mesh.faces.shape[0]
        stats.terrain_centre_error_m_max = float(err.max()) if err.size else None
        extras["terrain"] = {"grid": [req.cols, req.rows], "max_error_m": max_error_m,
                             "sun_time_utc": when if texture else None,
                             "centre_error_m": {"rms": float(np.sqrt(np.mean(err ** 2))) if err.size else None,
                                                "max": stats.terrain_centre_error_m_max}}
    else:
        extras["terrain"] = {"left_out": "no grid cell has terrain data at its four corners"}


def _add_tracks(scene, stats: GltfStats, r, tracks: dict, frame: LocalFrame) -> None:
    """A node per entity with a track of two points or more: its line segments, coloured by
    coalition, its identity in the mesh's extras."""
    for entity_id in sorted(tracks):
        info = r.entities.get(entity_id)
        meta = _entity_extras(info)
        name = f"{info.name if info is not None and info.name else 'entity'} #{entity_id}"
        segments = [enu_to_gltf(frame.to_local(seg.ecef)) for seg in tracks[entity_id].segments]
        lines = [s for s in segments if len(s) >= 2]
        if not lines:
            continue
        path = polylines(lines)
        rgba = COALITION_RGBA.get(meta.get("coalition", "neutral"), COALITION_RGBA["neutral"])
        path.colors = np.tile(np.array(rgba, np.uint8), (len(path.entities), 1))
        segs = tracks[entity_id].segments
        path.metadata.update({**meta, "world_time_s": [float(segs[0].times[0]), float(segs[-1].times[-1])]})
        scene.add_geometry(path, node_name=name, geom_name=name)
        stats.tracks += 1
        stats.track_points += sum(len(s) for s in lines)


def _add_target_areas(scene, stats: GltfStats, r, terrain, frame: LocalFrame) -> None:
    """A node per target area of the recorded scenario: its outline TARGET_AREA_LIFT_M above the
    terrain (above MSL 0 without a terrain)."""
    undulation = float(r.header.geoid_undulation_m)
    for area in _target_areas(r):
        outline = _outline(area.polygon, TARGET_AREA_STEP_M)
        ground = np.zeros(len(outline))
        if terrain is not None:
            ground = outline_ground(np.asarray(terrain.heights(outline[:, 0], outline[:, 1]).height_msl_m, float))
        where = geodetic_to_ecef(outline[:, 0], outline[:, 1], ground + TARGET_AREA_LIFT_M + undulation)
        path = polylines([enu_to_gltf(frame.to_local(where))])
        path.colors = np.tile(np.array(TARGET_AREA_RGBA, np.uint8), (len(path.entities), 1))
        path.metadata.update({"target_area": area.name, "detail_m": area.detail_m,
                              "polygon_lat_lon_deg": [list(v) for v in area.polygon]})
        scene.add_geometry(path, node_name=f"target area {area.name}", geom_name=f"target area {area.name}")
        stats.target_areas += 1


UNPLACED_EVENTS = ("join", "leave")  # a session's, not something that happened at a place


def _add_events(scene, extras: dict, stats: GltfStats, r, frame: LocalFrame) -> None:
    """The events: a point each where it has a position (node "events"); all of them in the
    scene's extras."""
    import trimesh

    undulation = float(r.header.geoid_undulation_m)
    # Every event is listed; those where something happened to an entity have a point (sessions
    # joining and leaving are not placed, nor an event without a whole position).
    skipped: list = []
    events = [ev.event for ev in r.events(skipped)]
    stats.skipped += [s for s in skipped if s not in stats.skipped]
    is_placed = [e.kind not in UNPLACED_EVENTS and all(map(math.isfinite, (e.lat_deg, e.lon_deg, e.alt_msl_m)))
                 for e in events]
    placed = [e for e, p in zip(events, is_placed) if p]
    if placed:
        where = geodetic_to_ecef([e.lat_deg for e in placed], [e.lon_deg for e in placed],
                                 np.array([e.alt_msl_m for e in placed]) + undulation)
        cloud = trimesh.PointCloud(enu_to_gltf(frame.to_local(where)))
        cloud.metadata["events"] = "the events of extras.sortie.events with a position, in that order"
        scene.add_geometry(cloud, node_name="events", geom_name="events")
    extras["events"] = [{"time_s": e.time_s, "kind": e.kind, "entity_id": int(e.entity_id),
                         "lat_deg": _json_number(e.lat_deg), "lon_deg": _json_number(e.lon_deg),
                         "alt_msl_m": _json_number(e.alt_msl_m), "placed": p,
                         "detail": json.loads(e.detail_json) if e.detail_json else {}}
                        for e, p in zip(events, is_placed)]
    stats.events = len(events)


# -- the animated markers -------------------------------------------------------------------------

# Marker shapes in body axes (x forward, y right, z down), about 1 m long, scaled per entity kind
# so that they are seen from kilometres away: a dart for aircraft, a box for ground vehicles, a
# pyramid for anything else; faces wound counter-clockwise seen from outside (_outward).


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The faces of a convex shape, each wound so that its normal points away from the centre."""
    v = vertices.astype(np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    out = np.einsum("ij,ij->i", np.cross(b - a, c - a), (a + b + c) / 3.0 - v.mean(axis=0)) > 0.0
    return np.where(out[:, None], faces, faces[:, [0, 2, 1]]).astype(np.uint16)


_BOX = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.3, 0.3) for z in (0.0, -0.35)], np.float32)
MARKER_SHAPES = {
    "dart": (np.array([[1.0, 0.0, 0.0], [-0.6, -0.5, 0.0], [-0.6, 0.5, 0.0], [-0.6, 0.0, -0.3]], np.float32),
             np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])),
    "box": (_BOX, np.array([[0, 1, 3], [0, 3, 2], [4, 5, 7], [4, 7, 6], [0, 1, 5], [0, 5, 4],
                            [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 3, 7], [1, 7, 5]])),
    "pyramid": (np.array([[0.5, 0.5, 0.0], [0.5, -0.5, 0.0], [-0.5, -0.5, 0.0], [-0.5, 0.5, 0.0], [0.0, 0.0, -1.0]],
                         np.float32), np.array([[0, 1, 2], [0, 2, 3], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])),
}
MARKER_SHAPES = {k: (v, _outward(v, f)) for k, (v, f) in MARKER_SHAPES.items()}
MARKER_OF_KIND = {pb.ENTITY_KIND_AIRCRAFT: ("dart", 60.0), pb.ENTITY_KIND_GROUND: ("box", 15.0)}
MARKER_OTHER = ("pyramid", 10.0)
MARKER_SCALE_M = {kind: scale for kind, (_, scale) in MARKER_OF_KIND.items()}


def scene_rotations(quat_ecef2body: np.ndarray, frame: LocalFrame) -> np.ndarray:
    """(k, 4) glTF node rotations (x, y, z, w) taking a marker in body axes (x forward, y
    right, z down) into the scene's axes, sign-continuous along the track (so a viewer's
    slerp between two keys turns the short way).

    A recorded q_eb (w, x, y, z) takes body components to ECEF (server.acmi.attitude_deg:
    q_eb = q_en q_nb); ECEF to ENU is the frame's basis; ENU to glTF is (e, u, -n)."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(quat_ecef2body, dtype=np.float64)
    r_ecef_body = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # normalises the rounded quaternions
    enu_to_gltf_m = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    out = Rotation.from_matrix(enu_to_gltf_m @ frame.basis @ r_ecef_body).as_quat()
    flips = np.ones(len(out))
    flips[1:] = np.where(np.einsum("ij,ij->i", out[1:], out[:-1]) < 0.0, -1.0, 1.0)
    return out * np.cumprod(flips)[:, None]


def add_markers(gltf: dict, binary: bytearray, tracks: dict, entities: dict, frame: LocalFrame,
                t0_s: float, dt_s: float) -> int:
    """Add a marker (MARKER_SHAPES by kind, coloured by coalition) per track, animated along it: translation
    and rotation keys (LINEAR) at its export ticks, scale keys (STEP) hiding it where it was
    absent. Animation time 0 is world time ``t0_s``. Returns the markers added."""
    material_of = {}
    for coalition, rgba in COALITION_RGBA.items():
        gltf.setdefault("materials", []).append({
            "name": f"marker {coalition}", "pbrMetallicRoughness": {
                "baseColorFactor": [c / 255.0 for c in rgba], "metallicFactor": 0.0, "roughnessFactor": 0.8}})
        material_of[coalition] = len(gltf["materials"]) - 1
    mesh_of = {}  # (shape, coalition) -> mesh: the shapes' accessors shared by their colours
    for shape, (vertices, faces) in MARKER_SHAPES.items():
        pos = append_accessor(gltf, binary, vertices, "VEC3", target=ARRAY_BUFFER, bounds=True)
        idx = append_accessor(gltf, binary, faces.ravel(), "SCALAR", UNSIGNED_SHORT, ELEMENT_ARRAY_BUFFER)
        for coalition, material in material_of.items():
            gltf.setdefault("meshes", []).append({"name": f"marker {shape} {coalition}", "primitives": [
                {"attributes": {"POSITION": pos}, "indices": idx, "material": material}]})
            mesh_of[shape, coalition] = len(gltf["meshes"]) - 1
    samplers, channels, nodes = [], [], []
    end = max((seg.times[-1] for t in tracks.values() for seg in t.segments), default=t0_s)
    for entity_id in sorted(tracks):
        segs = tracks[entity_id].segments
        if not segs:
            continue
        info = entities.get(entity_id)
        meta = _entity_extras(info)
        times = (np.concatenate([s.times for s in segs]) - t0_s).astype(np.float32)
        if np.any(np.diff(times) <= 0.0):
            raise InvalidArgument("rate", f"entity {entity_id}: its keys are closer in time than float32 seconds "
                                          "resolve this far into the sortie; export at a lower rate", value=None)
        where = enu_to_gltf(frame.to_local(np.concatenate([s.ecef for s in segs]))).astype(np.float32)
        turn = scene_rotations(np.concatenate([s.quat for s in segs]), frame).astype(np.float32)
        shape, scale = MARKER_OF_KIND.get(info.kind if info is not None else None, MARKER_OTHER)
        coalition = meta.get("coalition") if meta.get("coalition") in COALITION_RGBA else "neutral"
        # Shown from each segment's first tick, hidden half a tick after its last (unless the
        # recording ends there), and hidden from time 0 if it appears later.
        keys = [(0.0, 0.0)] if segs[0].times[0] > t0_s else []
        for s in segs:
            keys.append((s.times[0] - t0_s, scale))
            if s.times[-1] < end:
                keys.append((s.times[-1] - t0_s + 0.5 * dt_s, 0.0))
        key_t = np.array([k[0] for k in keys], np.float32)
        key_s = np.repeat(np.array([k[1] for k in keys], np.float32)[:, None], 3, axis=1)
        node = len(gltf["nodes"])
        gltf["nodes"].append({"name": f"{meta.get('name') or 'entity'} #{entity_id} marker",
                              "mesh": mesh_of[shape, coalition],
                              "translation": where[0].tolist(), "rotation": turn[0].tolist(),
                              "scale": key_s[0].tolist(), "extras": meta})
        nodes.append(node)
        t_acc = append_accessor(gltf, binary, times, "SCALAR", bounds=True)
        for path, values, kind, interpolation, inputs in (
                ("translation", where, "VEC3", "LINEAR", t_acc), ("rotation", turn, "VEC4", "LINEAR", t_acc),
                ("scale", key_s, "VEC3", "STEP", append_accessor(gltf, binary, key_t, "SCALAR", bounds=True))):
            samplers.append({"input": inputs, "output": append_accessor(gltf, binary, values, kind),
                             "interpolation": interpolation})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path}})
    if nodes:
        gltf["scenes"][gltf.get("scene", 0)]["nodes"].extend(nodes)
        gltf.setdefault("animations", []).append({"name": "sortie", "samplers": samplers, "channels": channels,
                                                  "extras": {"time_zero_world_s": t0_s}})
    return len(nodes)


def _target_areas(r) -> tuple:
    """The recorded scenario's target areas (none where the header holds no scenario)."""
    if not r.header.scenario_toml:
        return ()
    from server.resim import recorded_scenario

    return recorded_scenario(r).target_areas


def outline_ground(height_msl_m: np.ndarray) -> np.ndarray:
    """The ground (m MSL) under a closed outline's (k,) points (:func:`_outline`: the last is the
    first) from the terrain's heights there, NaN where it has none (an area reaching past the
    DEM's edge): those take the heights of the nearest points on either side along the outline
    that have one, linearly by their place between them (round the closing vertex too), so the
    outline runs on at the ground's level past the edge instead of dropping to MSL 0 (hundreds
    of metres below the terrain of a mountain DEM). No height anywhere: MSL 0 (as without a
    terrain)."""
    h = np.asarray(height_msl_m, dtype=np.float64)
    ok = np.isfinite(h)
    if ok.all() or not ok.any():
        return np.nan_to_num(h)
    k = np.arange(h.size)
    known = k[ok]
    period = h.size - 1  # the last point is the first: the outline's ring of distinct points
    xp = np.r_[known[-1] - period, known, known[0] + period]
    fp = np.r_[h[known[-1]], h[known], h[known[0]]]
    return np.where(ok, h, np.interp(k, xp, fp))


def _outline(polygon, step_m: float) -> np.ndarray:
    """(k, 2) (lat, lon) degrees round a polygon's (lat, lon) vertices and back to the first,
    each edge cut into pieces of at most ``step_m`` (linear in degrees: a target area is a few
    kilometres across). Each edge goes the short way in longitude, as the scenario measures an
    area (its longitude differences wrapped into [-180, 180)): an area across the antimeridian
    is drawn across it, not round the world; longitudes come back within [-180, 180)."""
    v = np.asarray(polygon, dtype=np.float64)
    closed = np.vstack([v, v[:1]])
    m, n = radii_of_curvature(float(v[:, 0].mean()))
    out = [closed[:1]]
    for a, b in zip(closed[:-1], closed[1:]):
        d = np.array([b[0] - a[0], (b[1] - a[1] + 180.0) % 360.0 - 180.0])
        length = math.hypot(math.radians(d[0]) * m, math.radians(d[1]) * n * math.cos(math.radians(a[0])))
        pieces = max(1, math.ceil(length / step_m))
        t = np.arange(1, pieces + 1)[:, None] / pieces
        piece = a + t * d
        piece[-1] = b  # the vertex itself, not its sum
        out.append(piece)
    lat_lon = np.vstack(out)
    lon = lat_lon[:, 1]
    lat_lon[:, 1] = np.where(lon >= 180.0, lon - 360.0, np.where(lon < -180.0, lon + 360.0, lon))
    return lat_lon


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

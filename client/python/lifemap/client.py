"""A typed layer over lifemapd's gRPC API (proto/lifemap/v1): numpy arrays in and out.

Images travel uncompressed both ways (colour as raw RGB8, depth as raw uint16, result images as
raw bytes): nothing here needs an image codec, and the server saves its PNG encoding (~5-8 ms
per frame, docs/BENCHMARKS.md). A 640x480 frame is ~1.5 MB on the wire: fine on a LAN or
loopback; over a slow link use the C++ client or `lifemap stream`, which send PNG/JPEG.

Conventions are the API's (proto/lifemap/v1/common.proto): metres, radians, seconds since the
Unix epoch; a pose is T_world_camera as (tx, ty, tz, qx, qy, qz, qw).
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import os
import time
import urllib.parse
from typing import Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

import grpc
import numpy as np

from lifemap.v1 import admin_service_pb2 as admin_pb
from lifemap.v1 import admin_service_pb2_grpc as admin_grpc
from lifemap.v1 import common_pb2 as common_pb
from lifemap.v1 import frame_service_pb2 as frame_pb
from lifemap.v1 import frame_service_pb2_grpc as frame_grpc
from lifemap.v1 import map_service_pb2 as map_pb
from lifemap.v1 import model_service_pb2 as model_pb
from lifemap.v1 import model_service_pb2_grpc as model_grpc
from lifemap.v1 import map_service_pb2_grpc as map_grpc
from lifemap.v1 import place_service_pb2 as place_pb
from lifemap.v1 import place_service_pb2_grpc as place_grpc
from lifemap.v1 import visit_service_pb2 as visit_pb
from lifemap.v1 import visit_service_pb2_grpc as visit_grpc

Intrinsics = Tuple[float, float, float, float]  # fx, fy, cx, cy in pixels
PoseTuple = Tuple[float, float, float, float, float, float, float]  # tx ty tz qx qy qz qw

# Results are up to ~1.5 MB (raw images of a 640x480 frame); export chunks 1 MiB.
_MAX_MESSAGE_BYTES = 64 * 1024 * 1024

# ExportMap's formats by the names `lifemap export --what` uses.
_EXPORT_FORMATS = {
    "poses": map_pb.EXPORT_POSES_TUM,
    "cloud": map_pb.EXPORT_CLOUD_PLY,
    "octree": map_pb.EXPORT_OCTREE_BT,
    "octree-color": map_pb.EXPORT_OCTREE_OT,
    "semantic-cloud": map_pb.EXPORT_SEMANTIC_CLOUD_PLY,
    "semantic-summary": map_pb.EXPORT_SEMANTIC_SUMMARY_JSON,
    "map": map_pb.EXPORT_MAP_ARCHIVE,
    "occupancy": map_pb.EXPORT_OCCUPANCY_OCTREE_BT,
}


class Error(Exception):
    """A call lifemapd refused or could not answer, or a frame it rejected.

    `code` is the grpc.StatusCode (INVALID_ARGUMENT, NOT_FOUND, UNAUTHENTICATED, ...) and
    `details` the server's message, which says what was wrong and what to do.
    """

    def __init__(self, code: grpc.StatusCode, details: str):
        super().__init__(f"{code.name}: {details}")
        self.code = code
        self.details = details


def _status_code(number: int) -> grpc.StatusCode:
    for code in grpc.StatusCode:
        if code.value[0] == number:
            return code
    return grpc.StatusCode.UNKNOWN


def _raise_from(error: grpc.RpcError) -> Error:
    return Error(error.code(), error.details() or "")


@dataclasses.dataclass
class Frame:
    """One RGB-D frame to send: `color` H x W x 3 uint8 (RGB), `depth` H x W uint16 with
    metres = value / depth_scale (0 = no reading), registered to the colour camera."""

    color: np.ndarray
    depth: np.ndarray
    intrinsics: Optional[Intrinsics] = None  # None: the stream's
    depth_scale: Optional[float] = None  # None: the stream's
    pose: Optional[PoseTuple] = None  # T_world_camera, when the robot knows it
    timestamp_s: Optional[float] = None  # None: now


class FrameResult:
    """What lifemapd answered for one frame, with its per-pixel outputs as numpy arrays.

    Arrays are None where the output was not computed; `outputs` says why (e.g. no model is
    active for the map, so no `labels`). `raw` is the lifemap.v1.FrameResult message.
    """

    def __init__(self, message: frame_pb.FrameResult, visit_id: int = 0):
        self.raw = message
        self.visit_id = visit_id
        self.sequence = message.sequence
        self.timestamp_s = message.timestamp_s
        self.width = message.width
        self.height = message.height
        self.error: Optional[Error] = None
        if message.HasField("error"):
            self.error = Error(_status_code(message.error.code), message.error.message)
        self.pose: Optional[PoseTuple] = None
        if message.pose_source not in (common_pb.POSE_SOURCE_UNSPECIFIED,
                                       common_pb.POSE_SOURCE_NONE):
            p = message.pose
            self.pose = (p.tx, p.ty, p.tz, p.qx, p.qy, p.qz, p.qw)
        self.pose_source = common_pb.PoseSource.Name(message.pose_source)
        # The stored keyframe's id when this frame became one and is durably committed.
        self.keyframe_id: Optional[int] = (
            message.keyframe.keyframe_id if message.keyframe.committed else None)
        # True where the entropy mask prunes the pixel (a superjut likely to move, paper 000).
        mask = self._image(message.entropy.mask_raw)
        self.entropy_mask: Optional[np.ndarray] = None if mask is None else mask == 255
        # Neg-entropy x 255 per pixel (eq. 4, normalised): low scores are masked.
        self.entropy_score = self._image(message.entropy.score_raw)
        self.entropy_threshold = message.entropy.threshold
        # Class id per pixel by the map's forest (paper 002); 255 = no depth, not labelled.
        self.labels = self._image(message.labels.label_raw)
        self.label_confidence = self._image(message.labels.confidence_raw)
        self.classes = {c.class_id: c.name for c in message.labels.classes}
        # The visit's semantic octree rendered at this frame's pose; 255 = no label there.
        self.fused_labels = self._image(message.fused_labels.label_raw)
        moved = self._image(message.moved.mask_raw)
        self.moved_mask: Optional[np.ndarray] = None if moved is None else moved == 255
        self.place_matches: List[frame_pb.PlaceMatch] = list(message.place_matches)
        self.outputs = {
            common_pb.FrameOutput.Name(o.output): (o.computed, o.reason) for o in message.outputs
        }

    def _image(self, data: bytes) -> Optional[np.ndarray]:
        if not data:
            return None
        return np.frombuffer(data, dtype=np.uint8).reshape(self.height, self.width)

    def __repr__(self) -> str:
        parts = [f"sequence={self.sequence}"]
        if self.error is not None:
            parts.append(f"error={self.error}")
        if self.keyframe_id is not None:
            parts.append(f"keyframe_id={self.keyframe_id}")
        if self.entropy_mask is not None:
            parts.append(f"masked={self.entropy_mask.mean():.1%}")
        return f"FrameResult({', '.join(parts)})"


def _as_frame(item: Union[Frame, tuple, list], index: int) -> Frame:
    """A Frame, or a tuple (color, depth[, pose[, timestamp_s]]) made into one; anything else
    is the caller's mistake, named here (a dict used to fail with "unhashable type: 'slice'")."""
    if isinstance(item, Frame):
        return item
    if isinstance(item, (tuple, list)) and 2 <= len(item) <= 4:
        return Frame(item[0], item[1], pose=item[2] if len(item) > 2 else None,
                     timestamp_s=item[3] if len(item) > 3 else None)
    what = (f"a {type(item).__name__} of {len(item)} values" if isinstance(item, (tuple, list))
            else f"a {type(item).__name__}")
    raise TypeError(f"frame {index} is {what}: each frame must be a lifemap.Frame(color, depth, "
                    f"pose=..., timestamp_s=...) or a tuple (color, depth[, pose[, "
                    f"timestamp_s]])")


def _pose_message(pose: Sequence[float]) -> common_pb.Pose:
    if len(pose) != 7:
        raise ValueError(f"a pose is (tx, ty, tz, qx, qy, qz, qw), got {len(pose)} values")
    return common_pb.Pose(tx=pose[0], ty=pose[1], tz=pose[2], qx=pose[3], qy=pose[4],
                          qz=pose[5], qw=pose[6])


def _frame_message(color: np.ndarray, depth: np.ndarray, intrinsics: Sequence[float],
                   depth_scale: float, pose: Optional[Sequence[float]], timestamp_s: float,
                   sequence: int) -> common_pb.Frame:
    """Checks the arrays here, where the caller's line is in the traceback, not on the server."""
    color = np.asarray(color)
    depth = np.asarray(depth)
    if color.ndim != 3 or color.shape[2] != 3 or color.dtype != np.uint8:
        raise ValueError(f"color must be an H x W x 3 uint8 array (RGB), got shape "
                         f"{color.shape} dtype {color.dtype}")
    if depth.ndim != 2 or depth.dtype != np.uint16:
        raise ValueError(f"depth must be an H x W uint16 array, got shape {depth.shape} dtype "
                         f"{depth.dtype} (metres: multiply by depth_scale and cast)")
    if depth.shape != color.shape[:2]:
        raise ValueError(f"depth is {depth.shape[1]}x{depth.shape[0]} but color is "
                         f"{color.shape[1]}x{color.shape[0]}: register depth to the colour camera")
    if intrinsics is None or len(intrinsics) != 4:
        raise ValueError("intrinsics must be (fx, fy, cx, cy) in pixels")
    height, width = depth.shape
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    frame = common_pb.Frame(
        sequence=sequence,
        timestamp_s=timestamp_s,
        intrinsics=common_pb.CameraIntrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=width,
                                              height=height),
        depth=common_pb.DepthImage(encoding=common_pb.DEPTH_RAW_U16,
                                   data=depth.astype("<u2", copy=False).tobytes(),
                                   width=width, height=height, depth_scale=float(depth_scale)),
        color=common_pb.ColorImage(encoding=common_pb.COLOR_RAW_RGB8,
                                   data=np.ascontiguousarray(color).tobytes(), width=width,
                                   height=height))
    if pose is not None:
        frame.pose.CopyFrom(_pose_message(pose))
    return frame


def _bytes_of(value: Union[None, bytes, str, os.PathLike]) -> Optional[bytes]:
    """The bytes given, or the bytes of the file at the path given."""
    if value is None or isinstance(value, bytes):
        return value
    with open(value, "rb") as f:
        return f.read()


def _archive_map_name(data: bytes) -> str:
    """The map name in a map archive's manifest (its second line, JSON), "" if none: only to
    route the import through a cluster; the server reads the archive properly."""
    lines = data[:65536].split(b"\n", 2)
    if len(lines) < 2:
        return ""
    try:
        return str(json.loads(lines[1]).get("map", ""))
    except ValueError:
        return ""


def _chunks(message, data: bytes, **first):
    """`data` as messages of at most 1 MiB; the first also carries `first` (e.g. the name)."""
    chunk = 1 << 20
    yield message(data=data[:chunk], **first)
    for at in range(chunk, len(data), chunk):
        yield message(data=data[at:at + chunk])


# Fanned-out answers of a cluster's shards merged into one, as client/cluster_merge.cc does.
_SUMMED_STATS = ("maps", "visits", "keyframes", "db_bytes", "wal_bytes", "active_streams",
                 "frames_processed", "frames_rejected", "keyframes_committed", "process_cpu_s",
                 "resident_bytes")
_METHOD_ORDER = {frame_pb.MATCH_METHOD_FUSED: 0, frame_pb.MATCH_METHOD_ARCHITECTURE: 1,
                 frame_pb.MATCH_METHOD_APPEARANCE: 2}


def _merge_stats(parts: Sequence[admin_pb.Stats]) -> admin_pb.Stats:
    if len(parts) == 1:
        merged = admin_pb.Stats()
        merged.CopyFrom(parts[0])
        return merged
    merged = admin_pb.Stats()
    for name in _SUMMED_STATS:
        setattr(merged, name, sum(getattr(p, name) for p in parts))
    merged.uptime_s = min(p.uptime_s for p in parts)
    merged.limited_to_maps = any(p.limited_to_maps for p in parts)
    a = merged.appearance
    a.enabled = all(p.appearance.enabled for p in parts)
    a.has_vocabulary = all(p.appearance.has_vocabulary for p in parts)
    a.words = max(p.appearance.words for p in parts)
    for name in ("keyframes", "memory_bytes", "stored_keyframes"):
        setattr(a, name, sum(getattr(p.appearance, name) for p in parts))
    a.min_training_keyframes = max(p.appearance.min_training_keyframes for p in parts)
    return merged


def _merge_place_answers(parts, max_results: int) -> place_pb.QueryPlaceResponse:
    """parts: (shard, QueryPlaceResponse). Rankings by method (fused, architecture,
    appearance), best score first, at most max_results each; per query frame likewise."""
    merged = place_pb.QueryPlaceResponse()
    matches, frames, methods = [], {}, {}
    for shard, part in parts:
        matches.extend(part.matches)
        for f in part.frames:
            entry = frames.setdefault(f.index, place_pb.FrameAppearance(index=f.index))
            entry.matches.extend(f.matches)
            if not entry.reason:
                entry.reason = f.reason
        if not merged.descriptor_text:
            merged.descriptor_text = part.descriptor_text
        for m in part.method_status:
            computed, reasons = methods.setdefault(m.method, [False, []])
            methods[m.method][0] = computed or m.computed
            if not m.computed:
                reasons.append(f"{shard}: {m.reason}")
        merged.unreachable_shards.extend(part.unreachable_shards)
    matches.sort(key=lambda m: (_METHOD_ORDER.get(m.method, 3), -m.score))
    counts = {}
    for m in matches:
        counts[m.method] = counts.get(m.method, 0) + 1
        if counts[m.method] <= max_results:
            merged.matches.append(m)
    for index in sorted(frames):
        f = frames[index]
        best = sorted(f.matches, key=lambda m: -m.score)[:max_results]
        del f.matches[:]
        f.matches.extend(best)
        if best:
            f.reason = ""
        merged.frames.append(f)
    for method, (computed, reasons) in methods.items():
        merged.method_status.add(method=method, computed=computed,
                                 reason="" if computed else "; ".join(reasons))
    return merged


class Client:
    """A connection to one lifemapd.

    target: "host:port". api_key: the secret `lifemap keys create` printed (sent as
    'authorization: Bearer KEY'); None for a server on loopback without keys.
    root_certificates: the CA that signed the server's TLS certificate (PEM bytes or a path);
    giving it (or tls=True, for the system's CAs) connects over TLS. certificate_chain and
    private_key: this client's certificate for a server that asks for one (mTLS).
    timeout_s bounds each unary call; streams run as long as their frames come.
    Every failed call raises lifemap.Error with the gRPC code and the server's message.
    """

    def __init__(self, target: str, api_key: Optional[str] = None,
                 root_certificates: Union[None, bytes, str, os.PathLike] = None, *,
                 tls: bool = False,
                 certificate_chain: Union[None, bytes, str, os.PathLike] = None,
                 private_key: Union[None, bytes, str, os.PathLike] = None,
                 timeout_s: float = 60.0):
        if not target or ":" not in target:
            raise ValueError(f"target must be host:port, got {target!r}")
        options = [("grpc.max_receive_message_length", _MAX_MESSAGE_BYTES),
                   ("grpc.max_send_message_length", _MAX_MESSAGE_BYTES)]
        if root_certificates is not None or tls or certificate_chain is not None:
            credentials = grpc.ssl_channel_credentials(
                root_certificates=_bytes_of(root_certificates),
                private_key=_bytes_of(private_key),
                certificate_chain=_bytes_of(certificate_chain))
            self._channel = grpc.secure_channel(target, credentials, options)
        else:
            self._channel = grpc.insecure_channel(target, options)
        self._metadata = [("authorization", f"Bearer {api_key.strip()}")] if api_key else []
        # Calls that name only a visit are routed by the map it was seen in.
        self._visit_maps: Dict[int, str] = {}
        self._timeout_s = timeout_s
        self.maps_stub = map_grpc.MapServiceStub(self._channel)
        self.visits_stub = visit_grpc.VisitServiceStub(self._channel)
        self.frames_stub = frame_grpc.FrameServiceStub(self._channel)
        self.places_stub = place_grpc.PlaceServiceStub(self._channel)
        self.admin_stub = admin_grpc.AdminServiceStub(self._channel)
        self.models_stub = model_grpc.ModelServiceStub(self._channel)

    def close(self) -> None:
        self._channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _routed(self, map_name: str = "", shard: str = ""):
        """The call's metadata: the key, and for a cluster of shards behind nginx the map the
        call is about (`lifemap-map`, which nginx routes on) or the shard it is meant for
        (`lifemap-shard`). A lone server ignores both (docs/OPERATIONS.md "Several servers")."""
        metadata = list(self._metadata)
        if map_name:
            # Percent-encoded: a header must be printable ASCII, names are UTF-8 ("Küche" is
            # sent as "K%C3%BCche"; core/common/cluster_headers.h, which nginx's table matches).
            metadata.append(("lifemap-map", urllib.parse.quote(map_name, safe="")))
        if shard:
            metadata.append(("lifemap-shard", shard))
        return metadata

    def _call(self, method, request, map_name: str = "", shard: str = ""):
        try:
            return method(request, timeout=self._timeout_s,
                          metadata=self._routed(map_name, shard))
        except grpc.RpcError as e:
            raise _raise_from(e) from None

    def _remember(self, visit_id: int, map_name: str) -> None:
        if visit_id and map_name:
            self._visit_maps[visit_id] = map_name

    # --- the server -------------------------------------------------------------------------

    def server_info(self) -> admin_pb.ServerInfo:
        return self._call(self.admin_stub.GetServerInfo, admin_pb.GetServerInfoRequest())

    def rebuild_appearance_index(self, retrain: bool = False) -> admin_pb.AppearanceIndexInfo:
        """Re-reads every stored keyframe into the appearance index; `retrain` first trains a
        new vocabulary on them (else one is trained once 30 keyframes are stored). Admin key."""
        return self._call(self.admin_stub.RebuildAppearanceIndex,
                          admin_pb.RebuildAppearanceIndexRequest(retrain=retrain))

    # --- maps, visits, keyframes ------------------------------------------------------------

    def create_map(self, name: str, description: str = "", *,
                   entropy_threshold: float = 0.0) -> map_pb.Map:
        return self._call(self.maps_stub.CreateMap,
                          map_pb.CreateMapRequest(name=name, description=description,
                                                  entropy_threshold=entropy_threshold), name)

    def maps(self) -> List[map_pb.Map]:
        """Every map. Through a cluster's nginx, asked of every shard and merged; shards that
        do not answer are in `unreachable_shards` (see maps_response)."""
        return list(self.maps_response().maps)

    def maps_response(self) -> map_pb.ListMapsResponse:
        shards = self._shards()
        if not shards:
            return self._call(self.maps_stub.ListMaps, map_pb.ListMapsRequest())
        merged = map_pb.ListMapsResponse()
        for shard, part in zip(shards, self._fan_out(self.maps_stub.ListMaps,
                                                     map_pb.ListMapsRequest(), shards)):
            if isinstance(part, Error):
                merged.unreachable_shards.append(f"{shard}: {part.details}")
                continue
            merged.maps.extend(part.maps)
        merged.maps.sort(key=lambda m: m.name)
        return merged

    def _shards(self) -> List[str]:
        """The cluster's shards (GetServerInfo through nginx); [] for a lone server or a
        client connected straight to one shard."""
        return [s.name for s in self.server_info().shards]

    def _fan_out(self, method, request, shards: Sequence[str]) -> list:
        """`method(request)` on every shard at once: each shard's answer, or its Error."""
        def one(shard):
            try:
                return self._call(method, request, shard=shard)
            except Error as e:
                return e
        with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, len(shards))) as pool:
            return list(pool.map(one, shards))

    def get_map(self, name: str) -> map_pb.Map:
        return self._call(self.maps_stub.GetMap, map_pb.GetMapRequest(name=name), name)

    def delete_map(self, name: str) -> map_pb.DeleteMapResponse:
        return self._call(self.maps_stub.DeleteMap, map_pb.DeleteMapRequest(name=name), name)

    def visits(self, map_name: str) -> List[visit_pb.Visit]:
        visits = list(self._call(self.visits_stub.ListVisits,
                                 visit_pb.ListVisitsRequest(map=map_name), map_name).visits)
        for v in visits:
            self._remember(v.id, v.map)
        return visits

    def end_visit(self, visit_id: int) -> visit_pb.Visit:
        return self._call(self.visits_stub.EndVisit, visit_pb.EndVisitRequest(visit_id=visit_id),
                          self._visit_maps.get(visit_id, ""))

    def keyframes(self, map_name: str, visit_id: int = 0) -> List[map_pb.KeyframeSummary]:
        return list(self._call(self.maps_stub.ListKeyframes,
                               map_pb.ListKeyframesRequest(map=map_name, visit_id=visit_id),
                               map_name).keyframes)

    def keyframe(self, map_name: str, keyframe_id: int) -> map_pb.Keyframe:
        """The stored keyframe: colour (JPEG or PNG) and depth (the store's lossless formats)
        as stored, with its summary and superjuts (`lifemap keyframes get` writes them as
        files)."""
        return self._call(self.maps_stub.GetKeyframe,
                          map_pb.GetKeyframeRequest(map=map_name, keyframe_id=keyframe_id),
                          map_name)

    # --- frames -----------------------------------------------------------------------------

    def process(self, map_name: Optional[str], color: np.ndarray, depth: np.ndarray,
                intrinsics: Intrinsics, depth_scale: float = 5000.0,
                pose: Optional[PoseTuple] = None, *, timestamp_s: Optional[float] = None,
                sequence: int = 0, visit_id: int = 0,
                options: Optional[frame_pb.FrameOptions] = None) -> FrameResult:
        """One frame, answered at once. With map_name it may become a keyframe: of the open
        visit `visit_id` names, or else of a visit of its own, started for it and ended once it
        is answered (as `lifemap process` does: a frame never joins a visit unasked, such as
        one a stream left open, whose time gap would refuse it); map_name None stores nothing.
        A rejected frame raises lifemap.Error (INVALID_ARGUMENT, saying why)."""
        frame = _frame_message(color, depth, intrinsics, depth_scale, pose,
                               timestamp_s if timestamp_s is not None else time.time(), sequence)
        own_visit = 0
        if map_name and not visit_id:
            own_visit = self._call(self.visits_stub.StartVisit,
                                   visit_pb.StartVisitRequest(map=map_name), map_name).id
            self._remember(own_visit, map_name)
        request = frame_pb.ProcessFrameRequest(map=map_name or "", visit_id=visit_id or own_visit,
                                               frame=frame, options=self._options(options))
        try:
            result = FrameResult(self._call(self.frames_stub.ProcessFrame, request,
                                            map_name or ""), visit_id or own_visit)
        except BaseException:
            if own_visit:
                try:
                    self.end_visit(own_visit)
                except Error:
                    pass  # the call's own error is the one to raise
            raise
        if own_visit:
            self.end_visit(own_visit)
        if result.error is not None:
            raise result.error
        return result

    def stream(self, map_name: str, frames: Iterable[Union[Frame, tuple]], *,
               intrinsics: Optional[Intrinsics] = None, depth_scale: float = 5000.0,
               visit_id: int = 0, robot: str = "", visit_label: str = "",
               options: Optional[frame_pb.FrameOptions] = None) -> Iterator[FrameResult]:
        """Streams frames into a visit of map_name (visit_id 0: a new visit) and yields one
        FrameResult per frame, in order, as the server answers. Each frame is a Frame or a
        tuple (color, depth[, pose[, timestamp_s]]) using the stream's intrinsics and
        depth_scale. A result acknowledging a keyframe (keyframe_id set) is durable. A frame
        the server rejects yields a result with `error` set and the stream goes on; a failed
        stream raises lifemap.Error. Every result carries the visit's id (visit_id)."""
        start = frame_pb.StreamStart(map=map_name, visit_id=visit_id, robot=robot,
                                     visit_label=visit_label, options=self._options(options))

        failed: List[BaseException] = []  # the caller's frames' own error, raised here

        def requests():
            yield frame_pb.StreamFramesRequest(start=start)
            try:
                yield from frame_requests()
            except Exception as e:  # gRPC would only say "Exception iterating requests"
                failed.append(e)
                raise

        def frame_requests():
            for sequence, item in enumerate(frames):
                item = _as_frame(item, sequence)
                message = _frame_message(
                    item.color, item.depth,
                    item.intrinsics if item.intrinsics is not None else intrinsics,
                    item.depth_scale if item.depth_scale is not None else depth_scale,
                    item.pose,
                    item.timestamp_s if item.timestamp_s is not None else time.time(),
                    sequence)
                yield frame_pb.StreamFramesRequest(frame=message)

        responses = self.frames_stub.StreamFrames(requests(), metadata=self._routed(map_name))
        started_visit = 0
        try:
            for response in responses:
                if response.HasField("started"):
                    started_visit = response.started.visit_id
                    self._remember(started_visit, map_name)
                elif response.HasField("result"):
                    yield FrameResult(response.result, started_visit)
        except grpc.RpcError as e:
            if failed:
                raise failed[0] from None
            raise _raise_from(e) from None
        finally:
            responses.cancel()

    @staticmethod
    def _options(options: Optional[frame_pb.FrameOptions]) -> frame_pb.FrameOptions:
        """The caller's options with result images raw (numpy needs no codec for them)."""
        merged = frame_pb.FrameOptions()
        if options is not None:
            merged.CopyFrom(options)
        if merged.result_images in (common_pb.RESULT_IMAGES_DEFAULT, common_pb.RESULT_IMAGES_PNG):
            merged.result_images = common_pb.RESULT_IMAGES_RAW
        return merged

    # --- object-class models (paper 002's forest) --------------------------------------------

    def upload_model(self, model: Union[bytes, str, os.PathLike], name: str) -> model_pb.ModelInfo:
        """Uploads a model file (`lifemap train --out`), given as its bytes or its path."""
        return self._call(self.models_stub.UploadModel,
                          _chunks(model_pb.UploadModelChunk, _bytes_of(model), name=name))

    def activate_model(self, name: str, map_name: str = "") -> model_pb.ActivateModelResponse:
        """Labels the frames of map_name (empty: of every map without its own) with the model
        `name`; an empty name deactivates."""
        return self._call(self.models_stub.ActivateModel,
                          model_pb.ActivateModelRequest(name=name, map=map_name), map_name)

    def models(self) -> List[model_pb.ModelInfo]:
        return list(self._call(self.models_stub.ListModels, model_pb.ListModelsRequest()).models)

    # --- places -----------------------------------------------------------------------------

    def query_place(self, frames: Iterable[Union[Frame, tuple]] = (), *,
                    intrinsics: Optional[Intrinsics] = None, depth_scale: float = 5000.0,
                    visit_id: int = 0, max_results: int = 0,
                    methods: Sequence[str] = ()) -> place_pb.QueryPlaceResponse:
        """Which stored place, visit and keyframe these frames show (nothing is stored), or
        which other visits a stored visit (visit_id) matches. methods: "appearance",
        "architecture" (posed frames), or both (empty). Matches carry scores in [0, 1]; the
        thresholds to accept them at are in docs/RESULTS.md."""
        names = {"appearance": frame_pb.MATCH_METHOD_APPEARANCE,
                 "architecture": frame_pb.MATCH_METHOD_ARCHITECTURE}
        request = place_pb.QueryPlaceRequest(visit_id=visit_id, max_results=max_results)
        for m in methods:
            if m not in names:
                raise ValueError(f"methods are 'appearance' and 'architecture', got {m!r}")
            request.methods.append(names[m])
        for index, item in enumerate(frames):
            item = _as_frame(item, index)
            request.frames.append(_frame_message(
                item.color, item.depth,
                item.intrinsics if item.intrinsics is not None else intrinsics,
                item.depth_scale if item.depth_scale is not None else depth_scale, item.pose,
                item.timestamp_s if item.timestamp_s is not None else time.time(), index))
        if visit_id:
            return self._call(self.places_stub.QueryPlace, request,
                              self._visit_maps.get(visit_id, ""))
        shards = self._shards()
        if not shards:
            return self._call(self.places_stub.QueryPlace, request)
        # Through a cluster: every shard at once, the rankings merged by score, as the C++
        # client does (client/cluster_merge.h).
        parts, unreachable, refused = [], [], None
        for shard, part in zip(shards, self._fan_out(self.places_stub.QueryPlace, request,
                                                     shards)):
            if not isinstance(part, Error):
                parts.append((shard, part))
            elif part.code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                unreachable.append(f"{shard}: {part.details}")
            elif part.code == grpc.StatusCode.FAILED_PRECONDITION:
                refused = refused or part
                nothing = place_pb.QueryPlaceResponse()
                for m in (frame_pb.MATCH_METHOD_ARCHITECTURE, frame_pb.MATCH_METHOD_APPEARANCE):
                    if not request.methods or m in request.methods:
                        nothing.method_status.add(method=m, computed=False, reason=part.details)
                parts.append((shard, nothing))
            else:
                raise part
        merged = _merge_place_answers(parts, max_results or 10)
        merged.unreachable_shards.extend(unreachable)
        if not any(m.computed for m in merged.method_status) and refused is not None:
            raise refused
        if not parts:
            raise Error(grpc.StatusCode.UNAVAILABLE, "no shard answered: " + "; ".join(unreachable))
        return merged

    def stats(self) -> admin_pb.Stats:
        """The server's figures (GetStats). Through a cluster's nginx every shard's, summed
        (uptime the shortest); shards that do not answer are in `unreachable_shards`."""
        shards = self._shards()
        if not shards:
            return self._call(self.admin_stub.GetStats, admin_pb.GetStatsRequest())
        parts, unreachable = [], []
        for shard, part in zip(shards, self._fan_out(self.admin_stub.GetStats,
                                                     admin_pb.GetStatsRequest(), shards)):
            if not isinstance(part, Error):
                parts.append(part)
            elif part.code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                unreachable.append(f"{shard}: {part.details}")
            else:
                raise part
        if not parts:
            raise Error(grpc.StatusCode.UNAVAILABLE, "no shard answered: " + "; ".join(unreachable))
        merged = _merge_stats(parts)
        merged.unreachable_shards.extend(unreachable)
        return merged

    # --- export -----------------------------------------------------------------------------

    def export(self, map_name: str, what: str = "poses", *, visit_id: int = 0,
               out: Union[None, str, os.PathLike] = None) -> bytes:
        """ExportMap as `lifemap export --what` names it: poses (TUM text), cloud (PLY),
        occupancy (OctoMap .bt from the depth, no model needed), octree (semantic .bt),
        octree-color (.ot), semantic-cloud (PLY), semantic-summary (JSON), map (the whole map
        as an archive for import_map). Returns the bytes, and writes them to `out` when given.
        For a navigation grid see export_grid."""
        if what not in _EXPORT_FORMATS:
            raise ValueError(f"what must be one of {', '.join(_EXPORT_FORMATS)}, got {what!r}")
        request = map_pb.ExportMapRequest(map=map_name, format=_EXPORT_FORMATS[what],
                                          visit_id=visit_id)
        data, _ = self._export(request)
        if out is not None:
            with open(out, "wb") as f:
                f.write(data)
        return data

    def export_grid(self, map_name: str, out_dir: Union[None, str, os.PathLike] = None, *,
                    visit_id: int = 0, resolution_m: float = 0.0,
                    floor_z: Optional[float] = None, min_height_m: float = 0.0,
                    max_height_m: float = 0.0) -> Tuple[np.ndarray, map_pb.OccupancyGridInfo]:
        """The map's 2D occupancy grid between floor + min_height_m (default 0.10) and floor +
        max_height_m (default 1.50; floor estimated unless given), as map_server has it: an
        H x W uint8 array (0 occupied, 254 free, 205 unknown; row 0 = largest y) and its info
        (resolution, origin). With out_dir, also writes MAP.pgm and MAP.yaml there."""
        request = map_pb.ExportMapRequest(map=map_name,
                                          format=map_pb.EXPORT_OCCUPANCY_GRID_PGM,
                                          visit_id=visit_id, voxel_size_m=resolution_m)
        request.grid.min_height_m = min_height_m
        request.grid.max_height_m = max_height_m
        if floor_z is not None:
            request.grid.floor_z = floor_z
        pgm, last = self._export(request)
        info = last.grid
        header_end = 0
        for _ in range(4):  # "P5", the comment, "W H", "255": four lines
            header_end = pgm.index(b"\n", header_end) + 1
        cells = np.frombuffer(pgm, dtype=np.uint8, offset=header_end).reshape(info.height,
                                                                             info.width)
        if out_dir is not None:
            os.makedirs(out_dir, exist_ok=True)
            with open(os.path.join(out_dir, f"{map_name}.pgm"), "wb") as f:
                f.write(pgm)
            with open(os.path.join(out_dir, f"{map_name}.yaml"), "w") as f:
                f.write(f"image: {map_name}.pgm\nmode: trinary\n"
                        f"resolution: {info.resolution_m:.6f}\n"
                        f"origin: [{info.origin_x:.6f}, {info.origin_y:.6f}, 0.0]\nnegate: 0\n"
                        "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
        return cells, info

    def import_map(self, archive: Union[bytes, str, os.PathLike],
                   name: str = "") -> map_pb.Map:
        """Adds a map from an archive (export(..., "map") or `lifemap maps export`), given as
        its bytes or its path, under `name` (empty: the name it was exported under)."""
        data = _bytes_of(archive)
        return self._call(self.maps_stub.ImportMap, _chunks(map_pb.ImportChunk, data, name=name),
                          name or _archive_map_name(data))

    def _export(self, request: map_pb.ExportMapRequest) -> Tuple[bytes, map_pb.ExportChunk]:
        parts, last = [], map_pb.ExportChunk()
        try:
            for chunk in self.maps_stub.ExportMap(request, timeout=self._timeout_s * 10,
                                                  metadata=self._routed(request.map)):
                parts.append(chunk.data)
                if chunk.last:
                    last = chunk
        except grpc.RpcError as e:
            raise _raise_from(e) from None
        return b"".join(parts), last

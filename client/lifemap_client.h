// The lifemap C++ client library: what a robot links to talk to lifemapd.
//
//   auto client = lifemap::client::Client::Connect({"127.0.0.1:50051"});
//   auto stream = (*client)->OpenStream(start);           // one visit
//   (*stream)->Send(frame); (*stream)->Receive(&result);   // from two threads if you like
//
// Every call returns an absl::Status whose code is the server's gRPC code and whose message is
// the server's (or says the server cannot be reached). Messages are lifemap.v1 protobufs.
#pragma once

#include <cstdint>
#include <functional>
#include <istream>
#include <memory>
#include <ostream>
#include <string>
#include <utility>

#include "absl/status/statusor.h"
#include "core/common/cluster_headers.h"
#include "lifemap/v1/admin_service.pb.h"
#include "lifemap/v1/frame_service.pb.h"
#include "lifemap/v1/map_service.pb.h"
#include "lifemap/v1/model_service.pb.h"
#include "lifemap/v1/place_service.pb.h"
#include "lifemap/v1/visit_service.pb.h"

namespace lifemap::client {

// Through a cluster of shards behind nginx (issue 39) every call about one map carries its name
// in kMapHeader, and the calls over every map — ListMaps, QueryPlace by frames, GetStats — are
// fanned out to every shard at once (kShardHeader) and merged here (client/cluster_merge.h):
// core/common/cluster_headers.h. A lone server ignores both headers. Fanning out in the client
// needs no extra hop or process; a client connected straight to one shard sees that shard's
// maps alone.

struct ClientOptions {
  std::string target = "127.0.0.1:50051";  // HOST:PORT of lifemapd
  int max_message_bytes = 64 << 20;        // largest message this client accepts/sends
  double connect_timeout_s = 5.0;          // Connect() waits this long for the server
  double call_timeout_s = 60.0;            // deadline of unary calls (not of streams)
  // Sent with every call as `authorization: Bearer KEY` when not empty (ResolveApiKey).
  std::string api_key;
  // TLS: on when `tls` is set or any file is given. The server's certificate is verified
  // against `tls_ca_file` (PEM; empty: the system's roots); a client certificate and key
  // (PEM, both or neither) are presented to servers that require them (mTLS).
  bool tls = false;
  std::string tls_ca_file;
  std::string tls_cert_file;
  std::string tls_key_file;

  // The defaults, for the server at `target`.
  static ClientOptions At(std::string target) {
    ClientOptions options;
    options.target = std::move(target);
    return options;
  }
};

// The API key to send: `key` if given, else the first line of `key_file` if given, else
// $LIFEMAP_API_KEY, else "" (none). InvalidArgument for an unreadable or empty file.
absl::StatusOr<std::string> ResolveApiKey(const std::string& key, const std::string& key_file);

// One visit's frame stream. Send() and Receive() may run on two different threads; each of them
// is thread-compatible on its own.
class FrameStream {
 public:
  virtual ~FrameStream() = default;
  // The server's answer to the StreamStart (map and visit id).
  virtual const v1::StreamStarted& started() const = 0;
  // Queues a frame; blocks while the server applies flow control. False once the stream is
  // broken: call Finish() for the reason.
  virtual bool Send(const v1::Frame& frame) = 0;
  // Tells the server no more frames follow (results still arrive).
  virtual bool CloseSend() = 0;
  // The next result, in frame order; false when the server ended the stream.
  virtual bool Receive(v1::FrameResult* result) = 0;
  // After Receive() returned false: the stream's final status.
  virtual absl::Status Finish() = 0;
  // Aborts the stream (the server sees a cancellation).
  virtual void Cancel() = 0;
};

// OK for "HOST:PORT" (a name, an IPv4 address or a bracketed IPv6 one, and a port in 1-65535)
// or a gRPC URI ("unix:PATH", "dns:..."); INVALID_ARGUMENT saying what is wrong otherwise.
absl::Status ValidateTarget(const std::string& target);

class Client {
 public:
  // UNAVAILABLE with a hint when the server does not answer within connect_timeout_s (saying
  // so when the host name does not resolve); INVALID_ARGUMENT for a malformed target.
  static absl::StatusOr<std::unique_ptr<Client>> Connect(const ClientOptions& options);
  virtual ~Client() = default;

  virtual absl::StatusOr<v1::ServerInfo> GetServerInfo() = 0;
  virtual absl::StatusOr<v1::Stats> GetStats() = 0;
  // `name`: the file's name in the server's backup directory.
  virtual absl::StatusOr<v1::BackupResponse> Backup(const std::string& name) = 0;
  virtual absl::StatusOr<v1::CheckIntegrityResponse> CheckIntegrity() = 0;
  virtual absl::StatusOr<v1::VacuumResponse> Vacuum() = 0;
  virtual absl::StatusOr<v1::AppearanceIndexInfo> RebuildAppearanceIndex(bool retrain) = 0;
  virtual absl::StatusOr<v1::RetentionReport> ApplyRetention(
      const v1::ApplyRetentionRequest& request) = 0;
  virtual absl::StatusOr<v1::CreateApiKeyResponse> CreateApiKey(
      const v1::CreateApiKeyRequest& request) = 0;
  virtual absl::StatusOr<v1::ListApiKeysResponse> ListApiKeys() = 0;
  virtual absl::StatusOr<v1::ApiKey> RevokeApiKey(const std::string& name) = 0;
  virtual absl::StatusOr<v1::ListAuditEventsResponse> ListAuditEvents(
      const v1::ListAuditEventsRequest& request) = 0;
  // A shard reads the placement now; for a map moving away, once its writes have drained.
  virtual absl::StatusOr<v1::RefreshPlacementResponse> RefreshPlacement(const std::string& map) = 0;

  virtual absl::StatusOr<v1::Map> CreateMap(const std::string& name,
                                            const std::string& description) = 0;
  virtual absl::StatusOr<v1::ListMapsResponse> ListMaps() = 0;
  virtual absl::StatusOr<v1::Map> GetMap(const std::string& name) = 0;
  virtual absl::StatusOr<v1::Map> RenameMap(const std::string& name,
                                            const std::string& new_name) = 0;
  virtual absl::StatusOr<v1::DeleteMapResponse> DeleteMap(const std::string& name) = 0;
  virtual absl::StatusOr<v1::Map> UpdateMap(const v1::UpdateMapRequest& request) = 0;
  virtual absl::StatusOr<v1::ListKeyframesResponse> ListKeyframes(const std::string& map,
                                                                  uint64_t visit_id) = 0;
  virtual absl::StatusOr<v1::Keyframe> GetKeyframe(const std::string& map,
                                                   uint64_t keyframe_id) = 0;
  // Streams the export into `out`; returns the number of items (poses or points) written.
  // `left_out`, when given, receives the visits a map-level export left out (not in the map's
  // frame), each "visit N: why".
  // `grid`, when given, receives a grid export's OccupancyGridInfo (its last chunk's).
  virtual absl::StatusOr<uint64_t> ExportMap(const v1::ExportMapRequest& request, std::ostream* out,
                                             std::vector<std::string>* left_out = nullptr,
                                             v1::OccupancyGridInfo* grid = nullptr) = 0;
  // Adds a map from an archive (ExportMap EXPORT_MAP_ARCHIVE) read from `in`, sent in 1 MiB
  // chunks, under `name` ("" = the name it was exported under). No deadline: a large map takes
  // as long as its bytes take to send and store.
  // `keep_ids`: ImportChunk.keep_ids (a move between the shards of a cluster).
  virtual absl::StatusOr<v1::Map> ImportMap(std::istream* in, const std::string& name,
                                            bool keep_ids = false) = 0;
  // Rebuilds semantic octrees from stored keyframes; `on_visit` gets each visit's outcome as
  // the server decides it (no deadline: a large map takes minutes).
  virtual absl::Status RebuildSemanticOctrees(
      const v1::RebuildSemanticOctreesRequest& request,
      const std::function<void(const v1::SemanticOctreeRebuild&)>& on_visit) = 0;

  virtual absl::StatusOr<v1::Visit> StartVisit(const v1::StartVisitRequest& request) = 0;
  virtual absl::StatusOr<v1::Visit> EndVisit(uint64_t visit_id) = 0;
  // Deletes an ended visit with its keyframes (operator role; VisitService.DeleteVisit says
  // which visits are refused and why).
  virtual absl::StatusOr<v1::DeleteVisitResponse> DeleteVisit(uint64_t visit_id) = 0;
  virtual absl::StatusOr<v1::ListVisitsResponse> ListVisits(const std::string& map) = 0;
  // Retries anchoring the map's tracked visits not in its frame (one, or every ended one for
  // visit_id 0) against the appearance index as it is now; blocks until judged. A dry run
  // stores nothing and says what each candidate match would have done.
  virtual absl::StatusOr<v1::AnchorVisitsResponse> AnchorVisits(const std::string& map,
                                                                uint64_t visit_id,
                                                                bool dry_run) = 0;
  // The visit's anchor history, oldest first: anchored, revised, dropped, with why.
  virtual absl::StatusOr<v1::AnchorHistory> GetAnchorHistory(uint64_t visit_id) = 0;
  // What changed between two visits of the map (both in its frame): objects appeared,
  // vanished, moved; doors opened, closed. ~1.3 s for two visits of 500 keyframes.
  virtual absl::StatusOr<v1::VisitChanges> GetChanges(const std::string& map, uint64_t from_visit,
                                                      uint64_t to_visit) = 0;

  // Models (random forests from `lifemap train`). UploadModel sends the file in 1 MiB chunks.
  virtual absl::StatusOr<v1::ModelInfo> UploadModel(const std::string& name,
                                                    const std::string& bytes) = 0;
  virtual absl::StatusOr<v1::ListModelsResponse> ListModels() = 0;
  // map "" = the server default; name "" deactivates.
  virtual absl::StatusOr<v1::ActivateModelResponse> ActivateModel(const std::string& name,
                                                                  const std::string& map) = 0;
  virtual absl::StatusOr<v1::DeleteModelResponse> DeleteModel(const std::string& name) = 0;
  virtual absl::StatusOr<v1::ListClassesResponse> ListClasses(const std::string& map) = 0;

  // Places (architecture, paper 004).
  virtual absl::StatusOr<v1::QueryPlaceResponse> QueryPlace(
      const v1::QueryPlaceRequest& request) = 0;
  virtual absl::StatusOr<v1::ListPlacesResponse> ListPlaces(const std::string& map) = 0;

  virtual absl::StatusOr<v1::FrameResult> ProcessFrame(const v1::ProcessFrameRequest& request) = 0;
  // Opens a stream and waits for the server's StreamStarted; the error if it refuses.
  virtual absl::StatusOr<std::unique_ptr<FrameStream>> OpenStream(const v1::StreamStart& start) = 0;
};

// Builds a Frame from image files as they are on disk (no re-encoding): depth must be a 16-bit
// PNG (`depth_scale` units per metre), colour a PNG or JPEG. Checks both headers and sizes.
// An empty `rgb_path` leaves the colour out (for uses of depth alone, such as QueryPlace); the
// image size then comes from the depth.
absl::StatusOr<v1::Frame> FrameFromFiles(const std::string& rgb_path, const std::string& depth_path,
                                         double depth_scale, const v1::CameraIntrinsics& intrinsics,
                                         double timestamp_s, uint64_t sequence);

// Re-encodes a frame the way a robot should send it: PNG or raw colour as JPEG at
// `jpeg_quality` (JPEG kept as it is), PNG-16 or raw 16-bit depth as DEPTH_PALETTED (lossless:
// the same values). The server then decodes a 640x480 frame in ~1.5 ms instead of ~9 ms for
// PNG colour and PNG-16 depth, and the frame is ~4x smaller on the wire (docs/API.md, "Frame
// encodings"). Float depth is left as it is. InvalidArgument if an image cannot be decoded.
absl::StatusOr<v1::Frame> CompactFrame(const v1::Frame& frame, int jpeg_quality = 90);

}  // namespace lifemap::client

#include "server/placement/placement.h"

#include <pqxx/pqxx>

#include <mutex>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"

namespace lifemap::placement {
namespace {

// Any value; the same in every process that creates the tables.
constexpr long long kSchemaLockKey = 0x6c6966656d6170;  // "lifemap"

constexpr const char* kSchema = R"sql(
CREATE TABLE IF NOT EXISTS lifemap_shards (
  name text PRIMARY KEY,
  number serial UNIQUE,
  address text NOT NULL,
  state text NOT NULL DEFAULT 'active' CHECK (state IN ('active', 'draining')),
  added_s double precision NOT NULL,
  seen_s double precision NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS lifemap_maps (
  name text PRIMARY KEY,
  shard text NOT NULL REFERENCES lifemap_shards(name),
  state text NOT NULL DEFAULT 'active' CHECK (state IN ('active', 'moving')),
  move_to text REFERENCES lifemap_shards(name),
  move_from text REFERENCES lifemap_shards(name),
  move_phase text CHECK (move_phase IN ('frozen', 'copied', 'switched')),
  move_started_s double precision,
  placed_s double precision NOT NULL
);
CREATE UNIQUE INDEX IF NOT EXISTS lifemap_maps_name_nocase ON lifemap_maps (lower(name));
CREATE INDEX IF NOT EXISTS lifemap_maps_by_shard ON lifemap_maps (shard);
CREATE TABLE IF NOT EXISTS lifemap_keys (
  name text PRIMARY KEY,
  role text NOT NULL CHECK (role IN ('robot', 'operator', 'admin')),
  every_map boolean NOT NULL,
  map_names text[] NOT NULL DEFAULT '{}',
  secret_sha256 text NOT NULL,
  created_s double precision NOT NULL,
  revoked_s double precision NOT NULL DEFAULT 0,
  max_streams bigint NOT NULL DEFAULT 0,
  max_frames_per_s double precision NOT NULL DEFAULT 0,
  max_maps bigint NOT NULL DEFAULT 0,
  max_keyframes_per_map bigint NOT NULL DEFAULT 0,
  max_model_bytes bigint NOT NULL DEFAULT 0,
  max_visits_per_hour bigint NOT NULL DEFAULT 0
);
)sql";

bool ValidName(const std::string& s) {
  if (s.empty() || s.size() > 64) return false;
  for (char c : s) {
    if (!absl::ascii_isalnum(static_cast<unsigned char>(c)) && c != '.' && c != '_' && c != '-') {
      return false;
    }
  }
  return true;
}

MapPlacement MapFromRow(const pqxx::row& r) {
  MapPlacement m;
  m.map = r[0].as<std::string>();
  m.shard = r[1].as<std::string>();
  m.state = r[2].as<std::string>();
  m.move_to = r[3].is_null() ? "" : r[3].as<std::string>();
  m.move_from = r[4].is_null() ? "" : r[4].as<std::string>();
  m.move_phase = r[5].is_null() ? "" : r[5].as<std::string>();
  m.move_started_s = r[6].is_null() ? 0.0 : r[6].as<double>();
  m.placed_s = r[7].as<double>();
  return m;
}

Shard ShardFromRow(const pqxx::row& r) {
  Shard s;
  s.name = r[0].as<std::string>();
  s.address = r[1].as<std::string>();
  s.state = r[2].as<std::string>();
  s.added_s = r[3].as<double>();
  s.seen_s = r[4].as<double>();
  s.number = r[5].as<int64_t>();
  return s;
}

// Map names travel as one newline-separated text (names never hold a newline): libpqxx 6.4 has
// no array parameters.
constexpr const char* kKeyColumns =
    "name, role, every_map, array_to_string(map_names, E'\\n'), secret_sha256, created_s, "
    "revoked_s, max_streams, max_frames_per_s, max_maps, max_keyframes_per_map, "
    "max_model_bytes, max_visits_per_hour";

ClusterKey KeyFromRow(const pqxx::row& r) {
  ClusterKey k;
  k.name = r[0].as<std::string>();
  k.role = r[1].as<std::string>();
  k.every_map = r[2].as<bool>();
  const std::string names = r[3].as<std::string>();
  if (!names.empty()) k.map_names = absl::StrSplit(names, '\n');
  k.secret_sha256 = r[4].as<std::string>();
  k.created_s = r[5].as<double>();
  k.revoked_s = r[6].as<double>();
  k.max_streams = r[7].as<int64_t>();
  k.max_frames_per_s = r[8].as<double>();
  k.max_maps = r[9].as<int64_t>();
  k.max_keyframes_per_map = r[10].as<int64_t>();
  k.max_model_bytes = r[11].as<int64_t>();
  k.max_visits_per_hour = r[12].as<int64_t>();
  return k;
}

constexpr const char* kMapColumns =
    "name, shard, state, move_to, move_from, move_phase, move_started_s, placed_s";
constexpr const char* kShardColumns = "name, address, state, added_s, seen_s, number";

// A move lock: its own connection, holding a session-level advisory lock until closed.
class PgMoveLock final : public MoveLock {
 public:
  explicit PgMoveLock(std::unique_ptr<pqxx::connection> conn) : conn_(std::move(conn)) {}

 private:
  std::unique_ptr<pqxx::connection> conn_;
};

class PgPlacement final : public Placement {
 public:
  explicit PgPlacement(std::string uri) : uri_(std::move(uri)) {}

  absl::Status Init() {
    return Run([](pqxx::work& w) {
      w.exec_params("SELECT pg_advisory_xact_lock($1)", kSchemaLockKey);
      w.exec(kSchema);
      return absl::OkStatus();
    });
  }

  absl::Status AddShard(const std::string& name, const std::string& address,
                        double now_s) override {
    if (auto s = ValidateShardName(name); !s.ok()) return s;
    if (address.empty() || address.find(':') == std::string::npos) {
      return absl::InvalidArgumentError(absl::StrCat(
          "shard address '", address, "' has no port: give HOST:PORT of its gRPC port"));
    }
    return Run([&](pqxx::work& w) {
      auto r = w.exec_params(
          "INSERT INTO lifemap_shards (name, address, added_s) VALUES ($1, $2, $3) "
          "ON CONFLICT (name) DO NOTHING",
          name, address, now_s);
      if (r.affected_rows() == 0) {
        return absl::AlreadyExistsError(absl::StrCat("shard '", name, "' is already placed"));
      }
      return absl::OkStatus();
    });
  }

  absl::StatusOr<std::vector<Shard>> ListShards() override {
    std::vector<Shard> shards;
    auto s = Run([&](pqxx::work& w) {
      shards.clear();
      for (const auto& row :
           w.exec(absl::StrCat("SELECT ", kShardColumns, " FROM lifemap_shards ORDER BY name"))) {
        shards.push_back(ShardFromRow(row));
      }
      return absl::OkStatus();
    });
    if (!s.ok()) return s;
    return shards;
  }

  absl::StatusOr<Shard> GetShard(const std::string& name) override {
    Shard shard;
    auto s = Run([&](pqxx::work& w) {
      auto r = w.exec_params(
          absl::StrCat("SELECT ", kShardColumns, " FROM lifemap_shards WHERE name = $1"), name);
      if (r.empty()) return UnknownShard(name);
      shard = ShardFromRow(r[0]);
      return absl::OkStatus();
    });
    if (!s.ok()) return s;
    return shard;
  }

  absl::Status SetShardState(const std::string& name, const std::string& state) override {
    if (state != "active" && state != "draining") {
      return absl::InvalidArgumentError(
          absl::StrCat("shard state '", state, "': give active or draining"));
    }
    return Run([&](pqxx::work& w) {
      auto r = w.exec_params("UPDATE lifemap_shards SET state = $2 WHERE name = $1", name, state);
      return r.affected_rows() == 0 ? UnknownShard(name) : absl::OkStatus();
    });
  }

  absl::Status RemoveShard(const std::string& name) override {
    return Run([&](pqxx::work& w) {
      auto maps = w.exec_params(
          "SELECT name FROM lifemap_maps WHERE shard = $1 OR move_to = $1 OR move_from = $1 ORDER "
          "BY name LIMIT 11",
          name);
      if (!maps.empty()) {
        std::vector<std::string> names;
        for (const auto& row : maps) names.push_back(row[0].as<std::string>());
        if (names.size() > 10) names.back() = "...";
        return absl::FailedPreconditionError(absl::StrCat(
            "shard '", name, "' still holds maps (", absl::StrJoin(names, ", "),
            "): drain it and move them first (lifemap admin shards drain; lifemap maps move)"));
      }
      auto r = w.exec_params("DELETE FROM lifemap_shards WHERE name = $1", name);
      return r.affected_rows() == 0 ? UnknownShard(name) : absl::OkStatus();
    });
  }

  absl::Status Heartbeat(const std::string& shard, double now_s) override {
    return Run([&](pqxx::work& w) {
      auto r = w.exec_params("UPDATE lifemap_shards SET seen_s = $2 WHERE name = $1", shard, now_s);
      return r.affected_rows() == 0 ? UnknownShard(shard) : absl::OkStatus();
    });
  }

  absl::StatusOr<std::vector<MapPlacement>> ListMaps(const std::string& shard) override {
    std::vector<MapPlacement> maps;
    auto s = Run([&](pqxx::work& w) {
      maps.clear();
      const std::string select = absl::StrCat("SELECT ", kMapColumns, " FROM lifemap_maps");
      auto r =
          shard.empty()
              ? w.exec(select + " ORDER BY name")
              : w.exec_params(select + " WHERE shard = $1 OR move_to = $1 ORDER BY name", shard);
      for (const auto& row : r) maps.push_back(MapFromRow(row));
      return absl::OkStatus();
    });
    if (!s.ok()) return s;
    return maps;
  }

  absl::StatusOr<std::optional<MapPlacement>> FindMap(const std::string& map) override {
    std::optional<MapPlacement> found;
    auto s = Run([&](pqxx::work& w) {
      auto r = w.exec_params(
          absl::StrCat("SELECT ", kMapColumns, " FROM lifemap_maps WHERE lower(name) = lower($1)"),
          map);
      found.reset();
      if (!r.empty()) found = MapFromRow(r[0]);
      return absl::OkStatus();
    });
    if (!s.ok()) return s;
    return found;
  }

  absl::Status PlaceMap(const std::string& map, const std::string& shard, double now_s) override {
    return Run([&](pqxx::work& w) -> absl::Status {
      auto known = w.exec_params("SELECT 1 FROM lifemap_shards WHERE name = $1", shard);
      if (known.empty()) {
        return absl::FailedPreconditionError(
            absl::StrCat("shard '", shard, "' is not in the placement database"));
      }
      auto r = w.exec_params(
          "INSERT INTO lifemap_maps (name, shard, placed_s) VALUES ($1, $2, $3) "
          "ON CONFLICT DO NOTHING",
          map, shard, now_s);
      if (r.affected_rows() > 0) return absl::OkStatus();
      auto other =
          w.exec_params("SELECT name, shard FROM lifemap_maps WHERE lower(name) = lower($1)", map);
      if (other.empty()) return absl::AbortedError("the placement changed meanwhile: try again");
      return absl::AlreadyExistsError(
          absl::StrCat("map '", other[0][0].as<std::string>(), "' exists on shard '",
                       other[0][1].as<std::string>(),
                       "' (map names are unique across the cluster, ignoring case)"));
    });
  }

  absl::Status UnplaceMap(const std::string& map, const std::string& shard) override {
    return Run([&](pqxx::work& w) {
      auto r = w.exec_params("DELETE FROM lifemap_maps WHERE name = $1 AND shard = $2", map, shard);
      if (r.affected_rows() > 0) {
        w.exec_params(
            "UPDATE lifemap_keys SET map_names = array_remove(map_names, $1) "
            "WHERE $1 = ANY(map_names)",
            map);
      }
      return absl::OkStatus();
    });
  }

  absl::Status AddKey(const ClusterKey& k) override {
    return Run([&](pqxx::work& w) {
      auto r = w.exec_params(
          "INSERT INTO lifemap_keys (name, role, every_map, map_names, secret_sha256, created_s, "
          "revoked_s, max_streams, max_frames_per_s, max_maps, max_keyframes_per_map, "
          "max_model_bytes, max_visits_per_hour) VALUES ($1, $2, $3, "
          "string_to_array($4, E'\\n'), $5, $6, $7, $8, $9, $10, $11, $12, $13) "
          "ON CONFLICT (name) DO NOTHING",
          k.name, k.role, k.every_map, absl::StrJoin(k.map_names, "\n"), k.secret_sha256,
          k.created_s, k.revoked_s, k.max_streams, k.max_frames_per_s, k.max_maps,
          k.max_keyframes_per_map, k.max_model_bytes, k.max_visits_per_hour);
      if (r.affected_rows() == 0) {
        return absl::AlreadyExistsError(
            absl::StrCat("an API key named '", k.name,
                         "' exists in the cluster (revoked keys keep their names): choose "
                         "another name"));
      }
      return absl::OkStatus();
    });
  }

  absl::StatusOr<ClusterKey> RevokeKey(const std::string& name, double now_s) override {
    ClusterKey key;
    auto s = Run([&](pqxx::work& w) -> absl::Status {
      w.exec_params("UPDATE lifemap_keys SET revoked_s = $2 WHERE name = $1 AND revoked_s = 0",
                    name, now_s);
      auto r = w.exec_params(
          absl::StrCat("SELECT ", kKeyColumns, " FROM lifemap_keys WHERE name = $1"), name);
      if (r.empty()) {
        return absl::NotFoundError(
            absl::StrCat("no API key named '", name, "' in the cluster (lifemap keys list)"));
      }
      key = KeyFromRow(r[0]);
      return absl::OkStatus();
    });
    if (!s.ok()) return s;
    return key;
  }

  absl::StatusOr<std::vector<ClusterKey>> ListKeys() override {
    std::vector<ClusterKey> keys;
    auto s = Run([&](pqxx::work& w) {
      keys.clear();
      for (const auto& row :
           w.exec(absl::StrCat("SELECT ", kKeyColumns, " FROM lifemap_keys ORDER BY name"))) {
        keys.push_back(KeyFromRow(row));
      }
      return absl::OkStatus();
    });
    if (!s.ok()) return s;
    return keys;
  }

  absl::StatusOr<std::unique_ptr<MoveLock>> LockMove(const std::string& map) override {
    try {
      auto conn = std::make_unique<pqxx::connection>(uri_);
      pqxx::nontransaction n(*conn);
      auto r =
          n.exec_params("SELECT pg_try_advisory_lock(hashtext('lifemap-move:' || lower($1)))", map);
      if (!r[0][0].as<bool>()) {
        return absl::AbortedError(absl::StrCat(
            "another `lifemap maps move` of map '", map,
            "' is running now: wait for it (lifemap admin shards list shows the move)"));
      }
      return std::unique_ptr<MoveLock>(new PgMoveLock(std::move(conn)));
    } catch (const std::exception& e) {
      return absl::UnavailableError(absl::StrCat("the placement database is unreachable: ",
                                                 absl::StripAsciiWhitespace(e.what())));
    }
  }

  absl::Status BeginMove(const std::string& map, const std::string& to, double now_s) override {
    return Run([&](pqxx::work& w) -> absl::Status {
      auto known = w.exec_params("SELECT 1 FROM lifemap_shards WHERE name = $1", to);
      if (known.empty()) return UnknownShard(to);
      auto r = w.exec_params(
          "UPDATE lifemap_maps SET state = 'moving', move_to = $2, move_phase = 'frozen', "
          "move_started_s = $3 WHERE name = $1 AND state = 'active' AND shard <> $2",
          map, to, now_s);
      if (r.affected_rows() == 1) return absl::OkStatus();
      return NotInPhase(w, map, "active");
    });
  }

  absl::Status AdvanceMove(const std::string& map, const std::string& from_phase) override {
    const char* sql = nullptr;
    if (from_phase == "frozen") {
      sql =
          "UPDATE lifemap_maps SET move_phase = 'copied' WHERE name = $1 AND move_phase = "
          "'frozen'";
    } else if (from_phase == "copied") {
      sql =
          "UPDATE lifemap_maps SET move_from = shard, shard = move_to, move_to = NULL, "
          "move_phase = 'switched' WHERE name = $1 AND move_phase = 'copied'";
    } else if (from_phase == "switched") {
      sql =
          "UPDATE lifemap_maps SET state = 'active', move_from = NULL, move_phase = NULL, "
          "move_started_s = NULL WHERE name = $1 AND move_phase = 'switched'";
    } else {
      return absl::InvalidArgumentError(absl::StrCat("no move phase '", from_phase, "'"));
    }
    return Run([&](pqxx::work& w) -> absl::Status {
      auto r = w.exec_params(sql, map);
      if (r.affected_rows() == 1) return absl::OkStatus();
      return NotInPhase(w, map, from_phase);
    });
  }

  absl::Status AbortMove(const std::string& map) override {
    return Run([&](pqxx::work& w) -> absl::Status {
      auto r = w.exec_params(
          "UPDATE lifemap_maps SET state = 'active', move_to = NULL, move_phase = NULL, "
          "move_started_s = NULL WHERE name = $1 AND move_phase IN ('frozen', 'copied')",
          map);
      if (r.affected_rows() == 1) return absl::OkStatus();
      return NotInPhase(w, map, "frozen or copied");
    });
  }

 private:
  // Why a map is not in `phase`: unknown, or where it stands.
  static absl::Status NotInPhase(pqxx::work& w, const std::string& map, const std::string& phase) {
    auto r = w.exec_params(
        absl::StrCat("SELECT ", kMapColumns, " FROM lifemap_maps WHERE name = $1"), map);
    if (r.empty()) {
      return absl::NotFoundError(absl::StrCat("map '", map, "' is not placed on any shard"));
    }
    const MapPlacement m = MapFromRow(r[0]);
    if (m.state == "active") {
      return absl::FailedPreconditionError(absl::StrCat("map '", map, "' is on shard '", m.shard,
                                                        "' and not moving (wanted ", phase, ")"));
    }
    return absl::FailedPreconditionError(absl::StrCat(
        "map '", map, "' is moving ", m.move_phase == "switched" ? m.move_from : m.shard, " -> ",
        m.move_phase == "switched" ? m.shard : m.move_to, ", phase ", m.move_phase, " (wanted ",
        phase, ")"));
  }

  static absl::Status UnknownShard(const std::string& name) {
    return absl::NotFoundError(absl::StrCat(
        "shard '", name, "' is not in the placement database: lifemap admin shards list"));
  }

  // Runs `body` in one transaction, committed when it returns OK. A broken connection is
  // reopened once (PostgreSQL restarted); after that, UNAVAILABLE.
  template <typename Body>
  absl::Status Run(Body&& body) {
    std::lock_guard<std::mutex> lock(mu_);
    for (int attempt = 0;; ++attempt) {
      try {
        if (!conn_ || !conn_->is_open()) conn_ = std::make_unique<pqxx::connection>(uri_);
        pqxx::work w(*conn_);
        absl::Status s = body(w);
        if (s.ok()) w.commit();
        return s;
      } catch (const pqxx::broken_connection& e) {
        conn_.reset();
        if (attempt >= 1) {
          return absl::UnavailableError(absl::StrCat(
              "the placement database is unreachable (", absl::StripAsciiWhitespace(e.what()),
              "): is PostgreSQL up at the --placement address?"));
        }
      } catch (const pqxx::sql_error& e) {
        return absl::InternalError(
            absl::StrCat("placement database: ", absl::StripAsciiWhitespace(e.what())));
      } catch (const std::exception& e) {
        conn_.reset();
        return absl::UnavailableError(
            absl::StrCat("placement database: ", absl::StripAsciiWhitespace(e.what())));
      }
    }
  }

  const std::string uri_;
  std::mutex mu_;
  std::unique_ptr<pqxx::connection> conn_;
};

}  // namespace

absl::Status ValidateShardName(const std::string& name) {
  if (ValidName(name)) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat(
      "shard name '", name, "' must be 1-64 characters of letters, digits, '.', '_' or '-'"));
}

absl::StatusOr<std::unique_ptr<Placement>> Placement::Open(const std::string& uri) {
  if (uri.empty()) {
    return absl::InvalidArgumentError(
        "no placement database: give --placement postgresql://USER@HOST:PORT/DB");
  }
  auto placement = std::make_unique<PgPlacement>(uri);
  if (auto s = placement->Init(); !s.ok()) return s;
  return std::unique_ptr<Placement>(std::move(placement));
}

}  // namespace lifemap::placement

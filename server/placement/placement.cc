#include "server/placement/placement.h"

#include <pqxx/pqxx>

#include <mutex>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

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
      w.exec_params("DELETE FROM lifemap_maps WHERE name = $1 AND shard = $2", map, shard);
      return absl::OkStatus();
    });
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

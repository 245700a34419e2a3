// A thin RAII layer over the SQLite C API: a connection with a cache of prepared statements,
// and statements that are bound, stepped and reset (LevelDB db_bench_sqlite3 style). No SQL is
// ever built from values: values are always bound.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <unordered_map>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

struct sqlite3;
struct sqlite3_stmt;

namespace lifemap::store {

class Statement {
 public:
  Statement(sqlite3* db, sqlite3_stmt* stmt) : db_(db), stmt_(stmt) {}
  ~Statement();
  Statement(const Statement&) = delete;
  Statement& operator=(const Statement&) = delete;

  // Parameters are 1-based as in SQLite.
  Statement& Bind(int index, int64_t value);
  Statement& Bind(int index, double value);
  Statement& Bind(int index, std::string_view text);
  Statement& BindBlob(int index, std::string_view bytes);
  Statement& BindNull(int index);

  // Steps once: true when a row is available, false when done. Errors carry SQLite's message.
  absl::StatusOr<bool> Step();
  // Steps to completion, for statements that return no rows.
  absl::Status Run();

  int64_t ColumnInt(int column) const;
  double ColumnDouble(int column) const;
  std::string ColumnText(int column) const;
  std::string ColumnBlob(int column) const;
  bool ColumnIsNull(int column) const;

  // Clears bindings and rewinds; the connection's cache calls it before handing out a statement.
  void Reset();

 private:
  absl::Status BindError() const;
  sqlite3* db_;
  sqlite3_stmt* stmt_;
  int bind_error_ = 0;  // first bind error, reported by Step()
};

// Resets a cached statement when the scope ends, so a statement never stays mid-step.
class StatementScope {
 public:
  explicit StatementScope(Statement* s) : s_(s) {}
  ~StatementScope() { s_->Reset(); }
  StatementScope(const StatementScope&) = delete;
  StatementScope& operator=(const StatementScope&) = delete;
  Statement* operator->() { return s_; }
  Statement& operator*() { return *s_; }

 private:
  Statement* s_;
};

// One SQLite connection. Thread-compatible: callers serialise access (Store holds a mutex per
// connection).
class Database {
 public:
  // Opens (creating if `create`) the file. busy_timeout_ms bounds waits for other connections.
  static absl::StatusOr<std::unique_ptr<Database>> Open(const std::string& path, bool create,
                                                        bool read_only, int busy_timeout_ms);
  ~Database();
  Database(const Database&) = delete;
  Database& operator=(const Database&) = delete;

  // Runs one or more statements without parameters (schema, pragmas, BEGIN/COMMIT).
  absl::Status Exec(const std::string& sql);
  // A statement prepared once per connection and reused; wrap it in a StatementScope.
  absl::StatusOr<Statement*> Prepare(const std::string& sql);
  // Runs a single-value query such as "PRAGMA user_version".
  absl::StatusOr<int64_t> QueryInt(const std::string& sql);

  int64_t LastInsertRowId() const;
  int Changes() const;
  sqlite3* raw() { return db_; }

 private:
  explicit Database(sqlite3* db) : db_(db) {}
  sqlite3* db_;
  std::unordered_map<std::string, std::unique_ptr<Statement>> statements_;
};

// Maps an SQLite result code (and the connection's message) to a Status.
absl::Status SqliteError(sqlite3* db, int rc, absl::string_view what);

// BEGIN IMMEDIATE ... COMMIT; rolls back unless committed (early returns on error).
class Transaction {
 public:
  explicit Transaction(Database* db) : db_(db) {}
  absl::Status Begin() { return db_->Exec("BEGIN IMMEDIATE"); }
  absl::Status Commit() {
    auto s = db_->Exec("COMMIT");
    if (s.ok()) done_ = true;
    return s;
  }
  ~Transaction() {
    if (!done_) db_->Exec("ROLLBACK").IgnoreError();
  }

 private:
  Database* db_;
  bool done_ = false;
};

}  // namespace lifemap::store

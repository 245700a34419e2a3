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

  // How many parameters the statement has (the highest ?N).
  int ParameterCount() const;

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

  // From now on every commit on this connection first checks that the database file at its
  // path and its WAL are still the files this connection writes (same device and inode):
  // a file deleted, moved or replaced under a running server would take every later commit
  // with it at the next restart. Such a commit is rolled back instead, and the statement fails
  // FAILED_PRECONDITION (SQLITE_CONSTRAINT_COMMITHOOK). Call once the WAL exists.
  void GuardCommits();
  // OK while the files are in place; FAILED_PRECONDITION saying what happened otherwise (also
  // without GuardCommits: then only the main file is checked, against itself at Open).
  absl::Status CheckFilesInPlace() const;

 private:
  struct FileId {
    bool exists = false;
    uint64_t dev = 0, ino = 0;
  };
  explicit Database(sqlite3* db, std::string path) : db_(db), path_(std::move(path)) {}
  static FileId IdOf(const std::string& path);
  static int OnCommit(void* self);
  sqlite3* db_;
  const std::string path_;
  FileId file_;  // as opened
  FileId wal_;   // as GuardCommits found it (not `exists` before: the WAL is not checked)
  std::unordered_map<std::string, std::unique_ptr<Statement>> statements_;
};

// Maps an SQLite result code (and the connection's message and errno) to a Status whose
// message says what to do. `sql`, the statement that failed, is named only in INTERNAL errors
// (a bug to report): clients are never shown SQL for a full disk, a read-only file, a lock or a
// constraint.
absl::Status SqliteError(sqlite3* db, int rc, absl::string_view what, absl::string_view sql = "");
// True for a statement refused by a UNIQUE, CHECK or foreign-key constraint (callers turn it
// into ALREADY_EXISTS or NOT_FOUND); false for a commit refused because the database file is
// no longer in place (FAILED_PRECONDITION too, but nothing the caller can name).
bool IsConstraintViolation(const absl::Status& status);

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

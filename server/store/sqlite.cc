#include "server/store/sqlite.h"

#include <sqlite3.h>
#include <sys/stat.h>

#include <cerrno>
#include <cstring>

#include "absl/strings/cord.h"
#include "absl/strings/str_cat.h"
#include "core/common/utf8.h"

namespace lifemap::store {

namespace {

constexpr absl::string_view kFileLostPayload = "lifemap.store/file-lost";

absl::Status FileLost(absl::string_view message) {
  absl::Status s = absl::FailedPreconditionError(message);
  s.SetPayload(kFileLostPayload, absl::Cord("1"));
  return s;
}

}  // namespace

bool IsConstraintViolation(const absl::Status& status) {
  return absl::IsFailedPrecondition(status) && !status.GetPayload(kFileLostPayload).has_value();
}

absl::Status SqliteError(sqlite3* db, int rc, absl::string_view what, absl::string_view sql) {
  const std::string message =
      absl::StrCat(what, ": ", db ? sqlite3_errmsg(db) : sqlite3_errstr(rc), " (sqlite ", rc, ")");
  // A write refused by the file system for permissions or a read-only mount (EACCES, EPERM,
  // EROFS) is not a full disk, however SQLite codes it (SQLITE_READONLY*, or a failed write).
  const int err = db != nullptr ? sqlite3_system_errno(db) : 0;
  if ((rc & 0xff) == SQLITE_READONLY ||
      ((rc & 0xff) == SQLITE_IOERR && (err == EROFS || err == EACCES || err == EPERM))) {
    return absl::FailedPreconditionError(absl::StrCat(
        what, ": the database is read-only to lifemapd (", db ? sqlite3_errmsg(db) : "",
        err != 0 ? absl::StrCat("; ", std::strerror(err)) : "",
        "): nothing was written; give lifemapd's user write permission on the database file, its "
        "-wal and -shm and their directory, or remount it read-write, then restart lifemapd"));
  }
  // A full disk is SQLITE_FULL; a file-size limit (EFBIG) or a quota (EDQUOT) is a failed
  // write (SQLITE_IOERR_WRITE; SQLite does not keep that write's errno reliably, so a failing
  // disk reads the same). Either way the transaction was rolled back, nothing acknowledged is
  // lost, and the next write succeeds once there is room: RESOURCE_EXHAUSTED, retry later.
  // SQLITE_FULL with no disk error behind it is one of SQLite's own limits: an AUTOINCREMENT
  // counter at 2^63 - 1 (issue 52: a crafted archive's ids) or max_page_count. Freeing disk
  // space would not help, so the message says so.
  if ((rc & 0xff) == SQLITE_FULL && err != ENOSPC && err != EDQUOT && err != EFBIG) {
    return absl::ResourceExhaustedError(absl::StrCat(
        message,
        ": the database reached one of SQLite's own limits, not the disk's (most often a table's "
        "id counter at its maximum, 2^63 - 1); this write was not made and nothing acknowledged "
        "is lost. `lifemap admin check` names the table; see docs/OPERATIONS.md \"Id counters\""));
  }
  if ((rc & 0xff) == SQLITE_FULL || rc == SQLITE_IOERR_WRITE) {
    return absl::ResourceExhaustedError(absl::StrCat(
        message,
        ": the disk is full (or a file-size limit or quota was reached, or the disk failed) and "
        "this write was not made; free space or check the disk (writes succeed again without a "
        "restart)"));
  }
  if (rc == SQLITE_CONSTRAINT_COMMITHOOK) {
    return FileLost(absl::StrCat(
        what,
        ": not written: the database file (or its -wal) was deleted, moved or replaced while "
        "lifemapd ran, so a restart would not find this write; put the file back where it was "
        "and restart lifemapd (the server log says what was found)"));
  }
  switch (rc & 0xff) {
    case SQLITE_CONSTRAINT:
      return absl::FailedPreconditionError(message);
    case SQLITE_BUSY:
    case SQLITE_LOCKED:
      return absl::UnavailableError(message);
    case SQLITE_CORRUPT:
    case SQLITE_NOTADB:
      return absl::DataLossError(message);
    case SQLITE_CANTOPEN:
    case SQLITE_PERM:
      return absl::FailedPreconditionError(message);
    default:
      return absl::InternalError(
          sql.empty() ? message : absl::StrCat(message, " in '", sql.substr(0, 200), "'"));
  }
}

Statement::~Statement() { sqlite3_finalize(stmt_); }

Statement& Statement::Bind(int index, int64_t value) {
  const int rc = sqlite3_bind_int64(stmt_, index, value);
  if (rc != SQLITE_OK && bind_error_ == 0) bind_error_ = rc;
  return *this;
}

Statement& Statement::Bind(int index, double value) {
  const int rc = sqlite3_bind_double(stmt_, index, value);
  if (rc != SQLITE_OK && bind_error_ == 0) bind_error_ = rc;
  return *this;
}

Statement& Statement::Bind(int index, std::string_view text) {
  const int rc =
      sqlite3_bind_text64(stmt_, index, text.data(), text.size(), SQLITE_TRANSIENT, SQLITE_UTF8);
  if (rc != SQLITE_OK && bind_error_ == 0) bind_error_ = rc;
  return *this;
}

Statement& Statement::BindBlob(int index, std::string_view bytes) {
  // SQLITE_STATIC: the caller keeps the bytes alive until the statement is stepped and reset.
  const int rc = sqlite3_bind_blob64(stmt_, index, bytes.data(), bytes.size(), SQLITE_STATIC);
  if (rc != SQLITE_OK && bind_error_ == 0) bind_error_ = rc;
  return *this;
}

Statement& Statement::BindNull(int index) {
  const int rc = sqlite3_bind_null(stmt_, index);
  if (rc != SQLITE_OK && bind_error_ == 0) bind_error_ = rc;
  return *this;
}

absl::Status Statement::BindError() const {
  return SqliteError(db_, bind_error_, "binding a statement parameter");
}

int Statement::ParameterCount() const { return sqlite3_bind_parameter_count(stmt_); }

absl::StatusOr<bool> Statement::Step() {
  if (bind_error_ != 0) return BindError();
  const int rc = sqlite3_step(stmt_);
  if (rc == SQLITE_ROW) return true;
  if (rc == SQLITE_DONE) return false;
  return SqliteError(db_, rc, "the database", sqlite3_sql(stmt_));
}

absl::Status Statement::Run() {
  for (;;) {
    auto row = Step();
    if (!row.ok()) return row.status();
    if (!*row) return absl::OkStatus();
  }
}

int64_t Statement::ColumnInt(int column) const { return sqlite3_column_int64(stmt_, column); }

double Statement::ColumnDouble(int column) const { return sqlite3_column_double(stmt_, column); }

std::string Statement::ColumnText(int column) const {
  const auto* p = sqlite3_column_text(stmt_, column);
  if (p == nullptr) return std::string();
  // Text read back is valid UTF-8 whatever was stored (a row written by an older lifemapd, or by
  // hand): the server lists it in responses, and one bad byte makes a whole listing unreadable.
  return ToValidUtf8(absl::string_view(reinterpret_cast<const char*>(p),
                                       static_cast<size_t>(sqlite3_column_bytes(stmt_, column))));
}

std::string Statement::ColumnBlob(int column) const {
  const void* p = sqlite3_column_blob(stmt_, column);
  return p ? std::string(static_cast<const char*>(p),
                         static_cast<size_t>(sqlite3_column_bytes(stmt_, column)))
           : std::string();
}

bool Statement::ColumnIsNull(int column) const {
  return sqlite3_column_type(stmt_, column) == SQLITE_NULL;
}

void Statement::Reset() {
  sqlite3_reset(stmt_);
  sqlite3_clear_bindings(stmt_);
  bind_error_ = 0;
}

absl::StatusOr<std::unique_ptr<Database>> Database::Open(const std::string& path, bool create,
                                                         bool read_only, int busy_timeout_ms) {
  sqlite3* db = nullptr;
  int flags = read_only ? SQLITE_OPEN_READONLY : SQLITE_OPEN_READWRITE;
  if (create && !read_only) flags |= SQLITE_OPEN_CREATE;
  flags |= SQLITE_OPEN_NOMUTEX;  // we serialise access ourselves
  const int rc = sqlite3_open_v2(path.c_str(), &db, flags, nullptr);
  if (rc != SQLITE_OK) {
    absl::Status s = SqliteError(db, rc, absl::StrCat("opening database ", path));
    sqlite3_close(db);
    return s;
  }
  sqlite3_busy_timeout(db, busy_timeout_ms);
  sqlite3_extended_result_codes(db, 1);
  auto database = std::unique_ptr<Database>(new Database(db, path));
  database->file_ = IdOf(path);
  return database;
}

Database::FileId Database::IdOf(const std::string& path) {
  struct stat st {};
  if (stat(path.c_str(), &st) != 0) return {};
  return {true, static_cast<uint64_t>(st.st_dev), static_cast<uint64_t>(st.st_ino)};
}

void Database::GuardCommits() {
  wal_ = IdOf(path_ + "-wal");
  sqlite3_commit_hook(db_, &Database::OnCommit, this);
}

absl::Status Database::CheckFilesInPlace() const {
  const auto differs = [](const FileId& a, const FileId& b) {
    return a.exists != b.exists || a.dev != b.dev || a.ino != b.ino;
  };
  const FileId file = IdOf(path_);
  if (!file.exists) {
    return absl::FailedPreconditionError(absl::StrCat(
        "database file ", path_,
        " was deleted or moved while lifemapd ran: writes are refused, since a restart would not "
        "find them"));
  }
  if (differs(file, file_)) {
    return absl::FailedPreconditionError(absl::StrCat(
        "database file ", path_,
        " was replaced by another file while lifemapd ran: writes are refused, since they would go "
        "to the file this server opened, not the one a restart will open"));
  }
  // The WAL holds every commit not yet checkpointed: deleted, a restart loses them.
  if (wal_.exists && differs(IdOf(path_ + "-wal"), wal_)) {
    return absl::FailedPreconditionError(absl::StrCat(
        "the database's write-ahead log ", path_,
        "-wal was deleted or replaced while lifemapd ran: writes are refused, since a restart "
        "would lose them"));
  }
  return absl::OkStatus();
}

int Database::OnCommit(void* self) {
  // Non-zero turns the commit into a rollback.
  return static_cast<Database*>(self)->CheckFilesInPlace().ok() ? 0 : 1;
}

Database::~Database() {
  statements_.clear();  // finalize before closing
  sqlite3_close(db_);
}

absl::Status Database::Exec(const std::string& sql) {
  char* error = nullptr;
  const int rc = sqlite3_exec(db_, sql.c_str(), nullptr, nullptr, &error);
  if (rc != SQLITE_OK) {
    absl::Status s = SqliteError(db_, rc, "the database", sql);
    sqlite3_free(error);
    return s;
  }
  return absl::OkStatus();
}

absl::StatusOr<Statement*> Database::Prepare(const std::string& sql) {
  auto it = statements_.find(sql);
  if (it != statements_.end()) return it->second.get();
  sqlite3_stmt* stmt = nullptr;
  const int rc = sqlite3_prepare_v3(db_, sql.c_str(), static_cast<int>(sql.size()),
                                    SQLITE_PREPARE_PERSISTENT, &stmt, nullptr);
  if (rc != SQLITE_OK) return SqliteError(db_, rc, "preparing a statement", sql);
  auto [inserted, ok] = statements_.emplace(sql, std::make_unique<Statement>(db_, stmt));
  return inserted->second.get();
}

absl::StatusOr<int64_t> Database::QueryInt(const std::string& sql) {
  auto stmt = Prepare(sql);
  if (!stmt.ok()) return stmt.status();
  StatementScope scope(*stmt);
  auto row = scope->Step();
  if (!row.ok()) return row.status();
  if (!*row) return absl::InternalError(absl::StrCat("'", sql, "' returned no row"));
  return scope->ColumnInt(0);
}

int64_t Database::LastInsertRowId() const { return sqlite3_last_insert_rowid(db_); }

int Database::Changes() const { return sqlite3_changes(db_); }

}  // namespace lifemap::store

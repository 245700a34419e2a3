// Output helpers shared by the CLI commands: JSON for scripts, aligned text for people.
#pragma once

#include <string>
#include <vector>

#include <google/protobuf/message.h>

#include "absl/status/status.h"

namespace lifemap::cli {

// The message as JSON with proto field names and every field present (zeros included).
// `multiline` for a person reading a file, single-line for one-object-per-line output.
std::string ToJson(const google::protobuf::Message& message, bool multiline = true);

// With `json` (the --json flag), errors are also printed on stdout as one JSON object,
// {"error": {"code": "NOT_FOUND", "message": "..."}}, for scripts. Set once by main().
void SetJsonErrors(bool json);

// Prints "lifemap: <message> [CODE]" on stderr (and the JSON error, see SetJsonErrors) and
// returns 1, the exit code for errors from the server, the data or the system.
int Fail(const absl::Status& status);
// The same for a command line that cannot work as given; returns 2 (bad usage).
int UsageError(const std::string& message);

// "12.3 MB", "512 B".
std::string HumanBytes(uint64_t bytes);
// Stored text (a description, a robot's name, an audit event's request) as a human table or
// message shows it: control characters, newlines and invisible characters escaped
// (core/common/utf8.h EscapeForLog), so that no stored text can forge a row or drive the
// terminal (issue 52); `empty` when there is none.
std::string Shown(const std::string& text, const char* empty = "-");
// "2026-11-23 14:05:09 UTC".
std::string HumanTime(double seconds_since_epoch);

// The nearest-rank `percent` percentile (0..100) of `values`; 0 when empty.
double Percentile(std::vector<double> values, double percent);

}  // namespace lifemap::cli

// Output helpers shared by the CLI commands: JSON for scripts, aligned text for people.
#pragma once

#include <string>

#include <google/protobuf/message.h>

#include "absl/status/status.h"

namespace lifemap::cli {

// The message as JSON with proto field names and every field present (zeros included).
// `multiline` for a person reading a file, single-line for one-object-per-line output.
std::string ToJson(const google::protobuf::Message& message, bool multiline = true);

// Prints "lifemap: <message>" on stderr and returns the exit code for the status: 1 for
// errors from the server or the system, 2 for bad usage (INVALID_ARGUMENT raised locally).
int Fail(const absl::Status& status);

// "12.3 MB", "512 B".
std::string HumanBytes(uint64_t bytes);
// "2026-11-23 14:05:09 UTC".
std::string HumanTime(double seconds_since_epoch);

}  // namespace lifemap::cli

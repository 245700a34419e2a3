// UTF-8 text that is valid by construction. Protobuf's proto3 `string` fields must hold valid
// UTF-8: a reader refuses a whole message with one bad byte in one field, so every string the
// server writes into a response (and every text it stores, which it lists back later) passes
// through these. Written here rather than taken from protobuf (its validator is internal API)
// or absl (none public in the Debian version); the rules are RFC 3629's.
#pragma once

#include <cstddef>
#include <string>

#include "absl/strings/string_view.h"

namespace lifemap {

// True if `text` is well-formed UTF-8 (RFC 3629: no overlong forms, no surrogates, nothing
// above U+10FFFF). The empty string is valid.
bool IsValidUtf8(absl::string_view text);

// `text` with every byte that does not begin a well-formed sequence replaced by U+FFFD ("�").
// Valid text comes back unchanged.
std::string ToValidUtf8(absl::string_view text);

// The longest prefix of `text` of at most `max_bytes` bytes that does not end inside a
// character (a cut never leaves half of "é"). `text` is assumed valid; on invalid input the
// cut still never splits a well-formed sequence.
absl::string_view Utf8Prefix(absl::string_view text, size_t max_bytes);

}  // namespace lifemap

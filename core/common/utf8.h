// UTF-8 text that is valid by construction. Protobuf's proto3 `string` fields must hold valid
// UTF-8: a reader refuses a whole message with one bad byte in one field, so every string the
// server writes into a response (and every text it stores, which it lists back later) passes
// through these. Written here rather than taken from protobuf (its validator is internal API)
// or absl (none public in the Debian version); the rules are RFC 3629's.
#pragma once

#include <cstddef>
#include <optional>
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

// The code points of `text`, or nullopt if it is not well-formed UTF-8.
std::optional<std::u32string> Utf8CodePoints(absl::string_view text);

// True for code points that change how text around them is shown rather than being seen: C0 and
// C1 controls and DEL, the line and paragraph separators, bidirectional overrides and isolates
// (U+202A-U+202E, U+2066-U+2069, U+200E/F), zero-width characters (U+200B-U+200D, U+2060, the
// byte order mark) and noncharacters (U+FDD0-U+FDEF, U+xFFFE/F).
bool IsInvisibleOrControl(char32_t code_point);

// `text` made safe to print as one line of a log or a terminal: every C0/C1 control, DEL and
// ESC is written as an escape ("\n", "\r", "\t", "\x1b", "\u0085"), a backslash as "\\",
// and bytes that are not UTF-8 as "\xNN". A log line built from it cannot be split into two or
// recolour a terminal. Printable text (any language) comes back unchanged.
std::string EscapeForLog(absl::string_view text);

}  // namespace lifemap

#include "core/common/utf8.h"

#include <cstdint>
#include <cstdio>

namespace lifemap {
namespace {

// Length of the well-formed sequence that starts at text[i], or 0 if none does.
size_t SequenceLength(absl::string_view text, size_t i) {
  const auto byte = [&](size_t k) { return static_cast<uint8_t>(text[k]); };
  const uint8_t b0 = byte(i);
  if (b0 < 0x80) return 1;
  size_t n = 0;
  uint8_t lo = 0x80, hi = 0xBF;  // the allowed range of the second byte
  if (b0 >= 0xC2 && b0 <= 0xDF) {
    n = 2;
  } else if (b0 >= 0xE0 && b0 <= 0xEF) {
    n = 3;
    if (b0 == 0xE0) lo = 0xA0;  // overlong
    if (b0 == 0xED) hi = 0x9F;  // UTF-16 surrogates
  } else if (b0 >= 0xF0 && b0 <= 0xF4) {
    n = 4;
    if (b0 == 0xF0) lo = 0x90;  // overlong
    if (b0 == 0xF4) hi = 0x8F;  // above U+10FFFF
  } else {
    return 0;  // a continuation byte, C0/C1 (overlong) or F5..FF
  }
  if (i + n > text.size()) return 0;
  if (byte(i + 1) < lo || byte(i + 1) > hi) return 0;
  for (size_t k = 2; k < n; ++k) {
    if ((byte(i + k) & 0xC0) != 0x80) return 0;
  }
  return n;
}

}  // namespace

bool IsValidUtf8(absl::string_view text) {
  for (size_t i = 0; i < text.size();) {
    const size_t n = SequenceLength(text, i);
    if (n == 0) return false;
    i += n;
  }
  return true;
}

std::string ToValidUtf8(absl::string_view text) {
  if (IsValidUtf8(text)) return std::string(text);
  std::string out;
  out.reserve(text.size() + 8);
  for (size_t i = 0; i < text.size();) {
    const size_t n = SequenceLength(text, i);
    if (n == 0) {
      out += "\xEF\xBF\xBD";  // U+FFFD REPLACEMENT CHARACTER
      ++i;
    } else {
      out.append(text.data() + i, n);
      i += n;
    }
  }
  return out;
}

absl::string_view Utf8Prefix(absl::string_view text, size_t max_bytes) {
  if (text.size() <= max_bytes) return text;
  size_t end = 0;
  while (end < max_bytes) {
    const size_t n = SequenceLength(text, end);
    const size_t step = n == 0 ? 1 : n;
    if (end + step > max_bytes) break;
    end += step;
  }
  return text.substr(0, end);
}

std::optional<std::u32string> Utf8CodePoints(absl::string_view text) {
  std::u32string out;
  out.reserve(text.size());
  for (size_t i = 0; i < text.size();) {
    const size_t n = SequenceLength(text, i);
    if (n == 0) return std::nullopt;
    const auto byte = [&](size_t k) { return static_cast<uint8_t>(text[i + k]); };
    char32_t cp = 0;
    if (n == 1) cp = byte(0);
    if (n == 2) cp = ((byte(0) & 0x1Fu) << 6) | (byte(1) & 0x3Fu);
    if (n == 3) cp = ((byte(0) & 0x0Fu) << 12) | ((byte(1) & 0x3Fu) << 6) | (byte(2) & 0x3Fu);
    if (n == 4) {
      cp = ((byte(0) & 0x07u) << 18) | ((byte(1) & 0x3Fu) << 12) | ((byte(2) & 0x3Fu) << 6) |
           (byte(3) & 0x3Fu);
    }
    out.push_back(cp);
    i += n;
  }
  return out;
}

bool IsInvisibleOrControl(char32_t cp) {
  if (cp < 0x20 || (cp >= 0x7F && cp <= 0x9F)) return true;
  if (cp == 0x2028 || cp == 0x2029) return true;                   // line/paragraph separators
  if ((cp >= 0x202A && cp <= 0x202E) || (cp >= 0x2066 && cp <= 0x2069)) return true;  // bidi
  if (cp == 0x200E || cp == 0x200F || cp == 0x061C) return true;  // direction marks
  if ((cp >= 0x200B && cp <= 0x200D) || cp == 0x2060 || cp == 0xFEFF) return true;  // zero width
  if (cp >= 0xFDD0 && cp <= 0xFDEF) return true;                  // noncharacters
  if ((cp & 0xFFFE) == 0xFFFE) return true;                        // U+xFFFE, U+xFFFF
  return false;
}

std::string EscapeForLog(absl::string_view text) {
  std::string out;
  out.reserve(text.size());
  char buf[16];
  for (size_t i = 0; i < text.size();) {
    const size_t n = SequenceLength(text, i);
    const auto b0 = static_cast<uint8_t>(text[i]);
    if (n == 0) {
      std::snprintf(buf, sizeof buf, "\\x%02x", b0);
      out += buf;
      ++i;
      continue;
    }
    if (n == 1) {
      if (b0 == '\n') {
        out += "\\n";
      } else if (b0 == '\r') {
        out += "\\r";
      } else if (b0 == '\t') {
        out += "\\t";
      } else if (b0 == '\\') {
        out += "\\\\";
      } else if (b0 < 0x20 || b0 == 0x7F) {
        std::snprintf(buf, sizeof buf, "\\x%02x", b0);
        out += buf;
      } else {
        out += static_cast<char>(b0);
      }
      ++i;
      continue;
    }
    const auto cps = Utf8CodePoints(text.substr(i, n));
    const char32_t cp = (*cps)[0];
    if (IsInvisibleOrControl(cp)) {
      std::snprintf(buf, sizeof buf, "\\u%04x", static_cast<unsigned>(cp));
      out += buf;
    } else {
      out.append(text.data() + i, n);
    }
    i += n;
  }
  return out;
}

}  // namespace lifemap

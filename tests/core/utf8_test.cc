#include "core/common/utf8.h"

#include <string>

#include <gtest/gtest.h>

#include "core/common/cluster_headers.h"

namespace lifemap {
namespace {

TEST(Utf8, AcceptsWellFormedTextOfEveryLength) {
  EXPECT_TRUE(IsValidUtf8(""));
  EXPECT_TRUE(IsValidUtf8("plain ascii"));
  EXPECT_TRUE(IsValidUtf8("caf\xC3\xA9"));                   // é, 2 bytes
  EXPECT_TRUE(IsValidUtf8("\xE2\x82\xAC"));                  // €, 3 bytes
  EXPECT_TRUE(IsValidUtf8("\xF0\x9F\xA4\x96"));              // robot face, 4 bytes
  EXPECT_TRUE(IsValidUtf8(std::string("nul\0inside", 10)));  // NUL is a character
}

TEST(Utf8, RefusesHalfCharactersOverlongFormsSurrogatesAndStrayBytes) {
  EXPECT_FALSE(IsValidUtf8("\xC3"));              // é cut in half
  EXPECT_FALSE(IsValidUtf8("\xA9"));              // a lone continuation byte
  EXPECT_FALSE(IsValidUtf8("\xC0\xAF"));          // overlong '/'
  EXPECT_FALSE(IsValidUtf8("\xE0\x80\xAF"));      // overlong '/', 3 bytes
  EXPECT_FALSE(IsValidUtf8("\xED\xA0\x80"));      // a UTF-16 surrogate
  EXPECT_FALSE(IsValidUtf8("\xF4\x90\x80\x80"));  // above U+10FFFF
  EXPECT_FALSE(IsValidUtf8("\xFF"));
}

TEST(Utf8, ReplacesEachBadByteAndKeepsTheRest) {
  EXPECT_EQ(ToValidUtf8("caf\xC3\xA9"), "caf\xC3\xA9");
  EXPECT_EQ(ToValidUtf8("a\xFF"
                        "b"),
            "a\xEF\xBF\xBD"
            "b");
  EXPECT_EQ(ToValidUtf8("end\xC3"), "end\xEF\xBF\xBD");
  EXPECT_TRUE(IsValidUtf8(ToValidUtf8("\xED\xA0\x80\xC0\xAF\xF0\x9F")));
}

TEST(Utf8, APrefixNeverEndsInsideACharacter) {
  std::string text;
  for (int i = 0; i < 300; ++i) text += "\xC3\xA9";  // 300 x é = 600 bytes
  const absl::string_view cut = Utf8Prefix(text, 511);
  EXPECT_EQ(cut.size(), 510u);
  EXPECT_TRUE(IsValidUtf8(cut));
  EXPECT_EQ(Utf8Prefix(text, 512).size(), 512u);
  EXPECT_EQ(Utf8Prefix("\xF0\x9F\xA4\x96", 3), "");
  EXPECT_EQ(Utf8Prefix("short", 512), "short");
  // Every cut of a mixed string is valid.
  const std::string mixed = "a\xC3\xA9\xE2\x82\xAC\xF0\x9F\xA4\x96z";
  for (size_t n = 0; n <= mixed.size(); ++n) EXPECT_TRUE(IsValidUtf8(Utf8Prefix(mixed, n))) << n;
}

TEST(Utf8, CodePointsOfEveryLengthAndNoneOfBadText) {
  const auto cps = Utf8CodePoints("a\xC3\xA9\xE2\x82\xAC\xF0\x9F\xA4\x96");
  ASSERT_TRUE(cps.has_value());
  EXPECT_EQ(*cps, (std::u32string{U'a', 0xE9, 0x20AC, 0x1F916}));
  EXPECT_FALSE(Utf8CodePoints("end\xC3").has_value());
}

// Issue 52: stored text (robot names, descriptions, refused calls' text) reaches log lines and
// the CLI; it must not forge a line or recolour a terminal.
TEST(EscapeForLog, WritesControlsAsEscapesAndKeepsEveryScript) {
  EXPECT_EQ(EscapeForLog("K\xC3\xBC" "che \xE6\x9D\xB1\xE4\xBA\xAC"),
            "K\xC3\xBC" "che \xE6\x9D\xB1\xE4\xBA\xAC");
  EXPECT_EQ(EscapeForLog("robot\n[info] forged"), "robot\\n[info] forged");
  EXPECT_EQ(EscapeForLog("\x1b[31mred\r\t"), "\\x1b[31mred\\r\\t");
  EXPECT_EQ(EscapeForLog("back\\slash"), "back\\\\slash");
  EXPECT_EQ(EscapeForLog("bad\xFF"), "bad\\xff");
  EXPECT_EQ(EscapeForLog("c1\xC2\x85 bidi\xE2\x80\xAE"), "c1\\u0085 bidi\\u202e");
  EXPECT_EQ(EscapeForLog(std::string("nul\0x", 5)), "nul\\x00x");
}

// Issue 52: a map name travels in a gRPC header, which must be printable ASCII.
TEST(HeaderValue, PercentEncodesAllButUnreservedAndRoundTrips) {
  EXPECT_EQ(EncodeHeaderValue("lab-2_b.v1"), "lab-2_b.v1");  // older names unchanged
  EXPECT_EQ(EncodeHeaderValue("K\xC3\xBC" "che"), "K%C3%BCche");
  EXPECT_EQ(EncodeHeaderValue("B\xC3\xBCro 2"), "B%C3%BCro%202");
  EXPECT_EQ(EncodeHeaderValue("100%"), "100%25");
  for (const std::string& name : {std::string("\xE6\x9D\xB1\xE4\xBA\xAC"), std::string("a b%c~"),
                                 std::string("\x01\x7F\xFF", 3)}) {
    const std::string encoded = EncodeHeaderValue(name);
    for (const char c : encoded) EXPECT_TRUE(c > 0x20 && c < 0x7F) << encoded;
    EXPECT_EQ(DecodeHeaderValue(encoded), name);
  }
  EXPECT_FALSE(DecodeHeaderValue("bad%2").has_value());
  EXPECT_FALSE(DecodeHeaderValue("bad%zz").has_value());
}

}  // namespace
}  // namespace lifemap

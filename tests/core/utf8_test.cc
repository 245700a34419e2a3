#include "core/common/utf8.h"

#include <string>

#include <gtest/gtest.h>

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

}  // namespace
}  // namespace lifemap

#include "core/common/depth_codec.h"

#include <filesystem>
#include <random>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "core/common/image_codec.h"
#include "core/io/tum_dataset.h"
#include "tests/testing/test_util.h"

namespace lifemap {
namespace {

bool SameImage(const cv::Mat& a, const cv::Mat& b) {
  return a.size() == b.size() && a.type() == b.type() && cv::countNonZero(a != b) == 0;
}

// Sensor-like depth: smooth surfaces, holes and runs of no reading, the full 16-bit range.
cv::Mat SyntheticDepth(int w, int h, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> hole(0, 19);
  cv::Mat d(h, w, CV_16UC1);
  for (int r = 0; r < h; ++r) {
    for (int c = 0; c < w; ++c) {
      d.at<uint16_t>(r, c) = hole(rng) == 0 ? 0 : static_cast<uint16_t>(4000 + 7 * r + 3 * c);
    }
  }
  d(cv::Rect(0, 0, w / 4, h)).setTo(0);  // a column of no reading
  d.at<uint16_t>(h - 1, w - 1) = 65535;
  d.at<uint16_t>(h - 1, w - 2) = 1;
  return d;
}

TEST(Rvl, RoundTripsExactly) {
  for (const cv::Mat& d :
       {SyntheticDepth(64, 48, 1), SyntheticDepth(640, 480, 2),
        cv::Mat(cv::Mat::zeros(9, 7, CV_16UC1)), cv::Mat(9, 7, CV_16UC1, cv::Scalar(65535)),
        cv::Mat(1, 1, CV_16UC1, cv::Scalar(1))}) {
    const std::string bytes = EncodeRvl(d);
    EXPECT_TRUE(LooksLikeRvl(bytes));
    auto back = DecodeRvl(bytes);
    ASSERT_TRUE(back.ok()) << back.status();
    EXPECT_TRUE(SameImage(*back, d)) << d.cols << "x" << d.rows;
  }
}

TEST(Rvl, ImageEndingInEveryRunLengthRoundTrips) {
  // The encoder stops after a final run of zeros; whatever nibble that run ends on, the decoder
  // must find no data left over.
  for (int zeros = 0; zeros < 40; ++zeros) {
    cv::Mat d(1, 64, CV_16UC1, cv::Scalar(1234));
    if (zeros > 0) d(cv::Rect(64 - zeros, 0, zeros, 1)).setTo(0);
    auto back = DecodeRvl(EncodeRvl(d));
    ASSERT_TRUE(back.ok()) << zeros << ": " << back.status();
    EXPECT_TRUE(SameImage(*back, d)) << zeros;
  }
}

TEST(Rvl, RefusesDamagedData) {
  const std::string good = EncodeRvl(SyntheticDepth(64, 48, 3));
  EXPECT_FALSE(DecodeRvl("").ok());
  EXPECT_FALSE(DecodeRvl("RVL1").ok());
  EXPECT_FALSE(DecodeRvl("PNG1" + good.substr(4)).ok());
  EXPECT_FALSE(DecodeRvl(good.substr(0, good.size() - 4)).ok()) << "truncated";
  EXPECT_FALSE(DecodeRvl(good + std::string(4, '\0')).ok()) << "trailing words";
  std::string huge = good;
  huge[5] = huge[6] = huge[9] = huge[10] = '\x7f';  // 32k x 32k pixels
  auto refused = DecodeRvl(huge, 1 << 20);
  ASSERT_FALSE(refused.ok());
  EXPECT_NE(refused.status().message().find("refused"), std::string::npos);
  // Random damage gives an error or an image, never a crash.
  std::mt19937 rng(7);
  for (int i = 0; i < 2000; ++i) {
    std::string bad = good;
    for (int k = 0; k < 3; ++k) bad[12 + rng() % (bad.size() - 12)] = static_cast<char>(rng());
    (void)DecodeRvl(bad);
  }
}

TEST(PalettedDepth, RoundTripsExactlyWithAndWithoutAPalette) {
  cv::Mat wide(64, 600, CV_16UC1);  // 38400 distinct values: more than a palette pays for
  for (int i = 0; i < static_cast<int>(wide.total()); ++i) {
    wide.at<uint16_t>(i / 600, i % 600) = static_cast<uint16_t>(1 + i);
  }
  for (const cv::Mat& d :
       {SyntheticDepth(64, 48, 1), SyntheticDepth(640, 480, 2), wide,
        cv::Mat(cv::Mat::zeros(9, 7, CV_16UC1)), cv::Mat(9, 7, CV_16UC1, cv::Scalar(65535))}) {
    const std::string bytes = EncodePalettedDepth(d);
    auto back = DecodePalettedDepth(bytes);
    ASSERT_TRUE(back.ok()) << back.status();
    EXPECT_TRUE(SameImage(*back, d)) << d.cols << "x" << d.rows;
  }
}

TEST(PalettedDepth, RefusesDamagedData) {
  const std::string good = EncodePalettedDepth(SyntheticDepth(64, 48, 3));
  EXPECT_FALSE(DecodePalettedDepth("").ok());
  EXPECT_FALSE(DecodePalettedDepth(EncodeRvl(SyntheticDepth(8, 8, 1))).ok()) << "RVL is not LMD";
  EXPECT_FALSE(DecodePalettedDepth(good.substr(0, good.size() - 3)).ok()) << "truncated";
  EXPECT_FALSE(DecodePalettedDepth(good + "x").ok()) << "trailing bytes";
  std::string big_palette = good;
  big_palette[14] = '\x7f';  // palette larger than the data
  EXPECT_FALSE(DecodePalettedDepth(big_palette).ok());
  std::mt19937 rng(11);
  for (int i = 0; i < 2000; ++i) {
    std::string bad = good;
    for (int k = 0; k < 3; ++k) bad[rng() % bad.size()] = static_cast<char>(rng());
    (void)DecodePalettedDepth(bad);  // an error or an image, never a crash
  }
}

TEST(DepthCodecs, KeepTheSensorsValuesAndPalettedIsSmallerThanPng) {
  const std::string dir = testing::SharedDataDir() + "/tum_fr1_xyz_subset";
  if (!std::filesystem::exists(dir)) GTEST_SKIP() << dir << " is absent (../shared/data)";
  auto seq = io::ReadTumSequence(dir);
  ASSERT_TRUE(seq.ok()) << seq.status();
  ASSERT_FALSE(seq->frames.empty());
  const cv::Mat raw = cv::imread(seq->frames[0].depth_path, cv::IMREAD_ANYDEPTH);
  ASSERT_EQ(raw.type(), CV_16UC1);
  cv::Mat metres;
  raw.convertTo(metres, CV_32FC1, 1.0 / 5000.0);
  auto rvl = EncodeDepthRvl(metres, 5000.0);
  auto paletted = EncodeDepthPaletted(metres, 5000.0);
  auto png = EncodeDepthPng16(metres, 5000.0);
  ASSERT_TRUE(rvl.ok() && paletted.ok() && png.ok());
  auto back = DecodeDepthMetres({DepthEncoding::kPaletted, *paletted, raw.cols, raw.rows, 5000.0});
  ASSERT_TRUE(back.ok()) << back.status();
  cv::Mat units;
  back->convertTo(units, CV_16UC1, 5000.0);
  // Readings outside the default depth range are no reading after decoding, as for PNG-16.
  cv::Mat in_range = raw.clone();
  in_range.setTo(0, raw > 50 * 5000);
  in_range.setTo(0, raw < 0.05 * 5000);
  EXPECT_TRUE(SameImage(units, in_range)) << "lossless at the sensor's precision";
  auto from_rvl = DecodeDepthMetres({DepthEncoding::kRvl, *rvl, raw.cols, raw.rows, 5000.0});
  ASSERT_TRUE(from_rvl.ok()) << from_rvl.status();
  EXPECT_EQ(cv::countNonZero(*from_rvl != *back), 0);
  // Kinect depth at TUM's scale: PNG-16 ~114 KB, RVL ~162 KB, paletted ~55 KB.
  EXPECT_LT(paletted->size(), png->size() * 2 / 3);
  // A size that disagrees with the frame is refused.
  EXPECT_FALSE(
      DecodeDepthMetres({DepthEncoding::kPaletted, *paletted, raw.cols / 2, raw.rows, 5000.0})
          .ok());
}

}  // namespace
}  // namespace lifemap

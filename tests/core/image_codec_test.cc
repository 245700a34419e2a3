#include "core/common/image_codec.h"

#include <cstring>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "core/common/rgbd_frame.h"
#include "tests/testing/test_util.h"

namespace lifemap {
namespace {

using testing::JpegBytes;
using testing::PngBytes;

cv::Mat Depth16(int w, int h, uint16_t v) { return cv::Mat(h, w, CV_16UC1, cv::Scalar(v)); }
cv::Mat Color(int w, int h) { return cv::Mat(h, w, CV_8UC3, cv::Scalar(10, 20, 30)); }

TEST(ProbeImage, ReadsPngHeader) {
  auto h = ProbeImage(PngBytes(Depth16(64, 48, 1000)));
  ASSERT_TRUE(h.ok()) << h.status();
  EXPECT_EQ(h->format, ImageFormat::kPng);
  EXPECT_EQ(h->width, 64);
  EXPECT_EQ(h->height, 48);
  EXPECT_EQ(h->bit_depth, 16);
  EXPECT_EQ(h->channels, 1);
}

TEST(ProbeImage, ReadsJpegHeader) {
  auto h = ProbeImage(JpegBytes(Color(64, 48)));
  ASSERT_TRUE(h.ok()) << h.status();
  EXPECT_EQ(h->format, ImageFormat::kJpeg);
  EXPECT_EQ(h->width, 64);
  EXPECT_EQ(h->height, 48);
  EXPECT_EQ(h->channels, 3);
}

TEST(ProbeImage, RejectsTruncatedPng) {
  std::string png = PngBytes(Depth16(64, 48, 1000));
  png.resize(png.size() / 2);
  auto h = ProbeImage(png);
  ASSERT_FALSE(h.ok());
  EXPECT_NE(h.status().message().find("truncated"), std::string::npos) << h.status();
}

TEST(ProbeImage, RejectsTruncatedJpeg) {
  std::string jpeg = JpegBytes(Color(64, 48));
  jpeg.resize(jpeg.size() - 40);
  auto h = ProbeImage(jpeg);
  ASSERT_FALSE(h.ok());
  EXPECT_NE(h.status().message().find("truncated"), std::string::npos) << h.status();
}

TEST(ProbeImage, RejectsUnknownAndEmptyData) {
  EXPECT_TRUE(absl::IsInvalidArgument(ProbeImage("").status()));
  EXPECT_TRUE(absl::IsInvalidArgument(ProbeImage("GIF89a....").status()));
}

TEST(DecodeDepthMetres, Png16UsesScale) {
  const std::string png = PngBytes(Depth16(32, 24, 7500));
  auto d = DecodeDepthMetres({DepthEncoding::kPng16, png, 32, 24, 5000.0});
  ASSERT_TRUE(d.ok()) << d.status();
  EXPECT_FLOAT_EQ(d->at<float>(5, 5), 1.5f);
}

TEST(DecodeDepthMetres, RawU16AndF32) {
  std::vector<uint16_t> u16(32 * 24, 2000);
  const std::string raw(reinterpret_cast<const char*>(u16.data()), u16.size() * 2);
  auto d = DecodeDepthMetres({DepthEncoding::kRawU16, raw, 32, 24, 1000.0});
  ASSERT_TRUE(d.ok());
  EXPECT_FLOAT_EQ(d->at<float>(0, 0), 2.0f);

  std::vector<float> f32(32 * 24, 1.25f);
  f32[0] = std::nanf("");
  f32[1] = -3.0f;
  const std::string rawf(reinterpret_cast<const char*>(f32.data()), f32.size() * 4);
  auto df = DecodeDepthMetres({DepthEncoding::kRawF32, rawf, 32, 24, 0.0});
  ASSERT_TRUE(df.ok());
  EXPECT_FLOAT_EQ(df->at<float>(0, 0), 0.0f) << "NaN counts as no reading";
  EXPECT_FLOAT_EQ(df->at<float>(0, 1), 0.0f) << "negative counts as no reading";
  EXPECT_FLOAT_EQ(df->at<float>(0, 2), 1.25f);
}

TEST(DecodeDepthMetres, RejectsWrongRawSize) {
  const std::string raw(100, '\0');
  auto d = DecodeDepthMetres({DepthEncoding::kRawU16, raw, 32, 24, 1000.0});
  ASSERT_FALSE(d.ok());
  EXPECT_NE(d.status().message().find("needs 1536"), std::string::npos) << d.status();
}

TEST(DecodeDepthMetres, RejectsEightBitPngAndBadScale) {
  const std::string png8 = PngBytes(cv::Mat(24, 32, CV_8UC1, cv::Scalar(5)));
  EXPECT_TRUE(absl::IsInvalidArgument(
      DecodeDepthMetres({DepthEncoding::kPng16, png8, 32, 24, 5000.0}).status()));
  const std::string png = PngBytes(Depth16(32, 24, 10));
  for (double scale : {0.0, -1.0, std::nan("")}) {
    EXPECT_TRUE(absl::IsInvalidArgument(
        DecodeDepthMetres({DepthEncoding::kPng16, png, 32, 24, scale}).status()));
  }
}

TEST(DecodeDepthMetres, RejectsSizeDifferentFromFrame) {
  const std::string png = PngBytes(Depth16(32, 24, 10));
  auto d = DecodeDepthMetres({DepthEncoding::kPng16, png, 64, 48, 5000.0});
  ASSERT_FALSE(d.ok());
  EXPECT_NE(d.status().message().find("32x24"), std::string::npos) << d.status();
}

TEST(DecodeColorBgr, DecodesJpegPngAndRaw) {
  const cv::Mat c = Color(32, 24);
  auto j = DecodeColorBgr({ColorEncoding::kJpeg, JpegBytes(c), 32, 24});
  ASSERT_TRUE(j.ok()) << j.status();
  EXPECT_EQ(j->type(), CV_8UC3);
  auto p = DecodeColorBgr({ColorEncoding::kPng, PngBytes(c), 32, 24});
  ASSERT_TRUE(p.ok());
  EXPECT_EQ(p->at<cv::Vec3b>(0, 0), cv::Vec3b(10, 20, 30));
  std::string rgb(32 * 24 * 3, '\0');
  for (size_t i = 0; i < rgb.size(); i += 3) rgb[i] = static_cast<char>(255);  // red
  auto r = DecodeColorBgr({ColorEncoding::kRawRgb8, rgb, 32, 24});
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->at<cv::Vec3b>(0, 0), cv::Vec3b(0, 0, 255)) << "raw RGB arrives as BGR";
}

TEST(DecodeColorBgr, RejectsEncodingMismatch) {
  auto s = DecodeColorBgr({ColorEncoding::kJpeg, PngBytes(Color(32, 24)), 32, 24}).status();
  EXPECT_TRUE(absl::IsInvalidArgument(s));
  EXPECT_NE(s.message().find("declared JPEG"), std::string::npos) << s;
}

TEST(DecodeColorBgr, RejectsCorruptPngBody) {
  std::string png = PngBytes(Color(32, 24));
  // Keep the header and the IEND trailer but garble the compressed data in between.
  for (size_t i = 40; i + 12 < png.size(); ++i) png[i] = static_cast<char>(0x5a);
  EXPECT_TRUE(absl::IsInvalidArgument(DecodeColorBgr({ColorEncoding::kPng, png, 32, 24}).status()));
}

TEST(EncodeDepthPng16, RoundTripsAndDropsOutOfRange) {
  cv::Mat d(24, 32, CV_32FC1, cv::Scalar(1.2345f));
  d.at<float>(0, 0) = 20.0f;  // beyond 13.1 m at scale 5000
  d.at<float>(0, 1) = std::nanf("");
  auto png = EncodeDepthPng16(d, 5000.0);
  ASSERT_TRUE(png.ok());
  auto back = DecodeDepthMetres({DepthEncoding::kPng16, *png, 32, 24, 5000.0});
  ASSERT_TRUE(back.ok());
  EXPECT_NEAR(back->at<float>(5, 5), 1.2345f, 1e-4);
  EXPECT_EQ(back->at<float>(0, 0), 0.0f);
  EXPECT_EQ(back->at<float>(0, 1), 0.0f);
}

TEST(DecodeRgbdFrame, RejectsBadTimestampAndMismatchedColour) {
  const std::string depth = PngBytes(Depth16(32, 24, 5000));
  const std::string color = JpegBytes(Color(64, 48));
  EncodedRgbdFrame f;
  f.timestamp_s = 0.0;
  f.intrinsics = {30, 30, 16, 12, 32, 24};
  f.depth = {DepthEncoding::kPng16, depth, 0, 0, 5000.0};
  f.color = {ColorEncoding::kJpeg, color, 0, 0};
  EXPECT_NE(DecodeRgbdFrame(f).status().message().find("timestamp"), std::string::npos);
  f.timestamp_s = 1.0;
  const auto s = DecodeRgbdFrame(f).status();
  EXPECT_TRUE(absl::IsInvalidArgument(s));
  EXPECT_NE(s.message().find("64x48"), std::string::npos) << s;
}

TEST(ComputeDepthStats, CountsValidPixelsAndMedian) {
  cv::Mat d(10, 10, CV_32FC1, cv::Scalar(0.0f));
  for (int i = 0; i < 50; ++i) d.at<float>(i / 10, i % 10) = 1.0f + static_cast<float>(i % 3);
  const auto s = ComputeDepthStats(d);
  EXPECT_FLOAT_EQ(s.valid_fraction, 0.5f);
  EXPECT_FLOAT_EQ(s.median_m, 2.0f);
}

// Grey 8-bit images (the per-frame result images) take lifemap's own libpng path: any PNG
// decoder must read back exactly the same pixels, from a view into a larger image too.
TEST(EncodePng, GreyImagesRoundTripExactlyThroughAnyDecoder) {
  cv::Mat big(300, 400, CV_8UC1);
  cv::RNG rng(7);
  rng.fill(big, cv::RNG::UNIFORM, 0, 256);
  big(cv::Rect(0, 0, 200, 100)).setTo(3);  // a run of one value, as label images have
  for (const cv::Mat& image :
       {big, cv::Mat(big(cv::Rect(17, 23, 301, 199))), cv::Mat(1, 1, CV_8UC1, cv::Scalar(255))}) {
    auto png = EncodePng(image);
    ASSERT_TRUE(png.ok()) << png.status();
    auto header = ProbeImage(*png);
    ASSERT_TRUE(header.ok()) << header.status();
    EXPECT_EQ(header->width, image.cols);
    EXPECT_EQ(header->height, image.rows);
    EXPECT_EQ(header->channels, 1);
    const cv::Mat back =
        cv::imdecode(std::vector<uchar>(png->begin(), png->end()), cv::IMREAD_UNCHANGED);
    ASSERT_EQ(back.type(), CV_8UC1);
    EXPECT_EQ(cv::norm(back, image, cv::NORM_INF), 0.0);
  }
}

}  // namespace
}  // namespace lifemap

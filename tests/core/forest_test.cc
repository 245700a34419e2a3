#include "core/forest/forest.h"

#include "core/io/labeled_pcd.h"
#include "tests/testing/test_util.h"

#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>

#include <gtest/gtest.h>

namespace lifemap::forest {
namespace {

// Left half class 0, right half class 1, a 12-pixel band between them unlabelled. `by_depth`:
// the left half is a fronto-parallel plane and the right half a plane tilted away (depth grows
// 1 cm per pixel), one colour: a depth-depth feature across neighbours tells them apart.
// Otherwise one depth and two colours (red, blue).
LabeledImage Halves(bool by_depth, int w = 80, int h = 60) {
  LabeledImage im;
  im.depth_m = cv::Mat(h, w, CV_32FC1, cv::Scalar(1.5f));
  im.color_bgr = cv::Mat(h, w, CV_8UC3, cv::Scalar(128, 128, 128));
  im.labels = cv::Mat(h, w, CV_8UC1, cv::Scalar(0));
  im.labels(cv::Rect(w / 2, 0, w / 2, h)).setTo(1);
  im.labels(cv::Rect(w / 2 - 6, 0, 12, h)).setTo(kIgnore);
  if (by_depth) {
    for (int r = 0; r < h; ++r) {
      for (int c = w / 2; c < w; ++c) im.depth_m.at<float>(r, c) = 1.5f + 0.01f * (c - w / 2);
    }
  } else {
    im.color_bgr(cv::Rect(0, 0, w / 2, h)).setTo(cv::Scalar(0, 0, 220));
    im.color_bgr(cv::Rect(w / 2, 0, w / 2, h)).setTo(cv::Scalar(220, 0, 0));
  }
  return im;
}

TrainOptions Small() {
  TrainOptions o;
  o.trees = 2;
  o.max_depth = 8;
  o.pixels_per_image = 4000;
  o.candidates = 200;
  o.max_offset = 5;
  o.max_size = 4;
  return o;
}

// Over the labelled pixels.
double Accuracy(const Forest& f, const LabeledImage& im) {
  auto p = f.Predict(im.depth_m, im.color_bgr);
  EXPECT_TRUE(p.ok()) << p.status();
  const cv::Mat labelled = im.labels != kIgnore;
  return cv::countNonZero((p->labels == im.labels) & labelled) /
         static_cast<double>(cv::countNonZero(labelled));
}

TEST(Forest, LearnsSeparableCasesPerfectly) {
  for (bool by_depth : {true, false}) {
    const LabeledImage im = Halves(by_depth);
    auto forest = Forest::Train({im, im}, 2, Small());
    ASSERT_TRUE(forest.ok()) << forest.status();
    EXPECT_DOUBLE_EQ(Accuracy(*forest, im), 1.0) << (by_depth ? "depth" : "colour");
  }
}

TEST(Forest, TheFeatureShareDecidesWhatTheTreesCanSee) {
  // Colour halves on one depth: colour-only features learn them, depth-only cannot.
  const LabeledImage colour = Halves(/*by_depth=*/false);
  TrainOptions o = Small();
  o.depth_feature_share = 0.0f;
  auto by_colour = Forest::Train({colour, colour}, 2, o);
  ASSERT_TRUE(by_colour.ok()) << by_colour.status();
  EXPECT_DOUBLE_EQ(Accuracy(*by_colour, colour), 1.0);
  o.depth_feature_share = 1.0f;
  auto by_depth = Forest::Train({colour, colour}, 2, o);
  ASSERT_TRUE(by_depth.ok()) << by_depth.status();
  EXPECT_LT(Accuracy(*by_depth, colour), 0.75) << "depth is flat: nothing to learn from";
  o.depth_feature_share = 1.5f;
  EXPECT_EQ(Forest::Train({colour}, 2, o).status().code(), absl::StatusCode::kInvalidArgument);
}

// Class 1 appears in one image of ten, as a small patch whose colour differs slightly. Balanced
// within each image only, its samples are a small share of the tree's; globally balanced, they
// weigh as much as class 0's, and the leaves say so.
TEST(Forest, GlobalBalanceWeighsARareClassAsMuchAsACommonOne) {
  std::vector<LabeledImage> images;
  for (int i = 0; i < 10; ++i) {
    LabeledImage im = Halves(/*by_depth=*/false);
    im.labels.setTo(0);
    if (i == 0) im.labels(cv::Rect(0, 0, 40, 60)).setTo(1);
    images.push_back(im);
  }
  TrainOptions o = Small();
  o.trees = 1;
  o.max_depth = 1;  // one split at most: the root's leaves show the weighting
  o.pixels_per_image = 400;
  auto Share = [&](bool global) {
    o.global_balance = global;
    auto forest = Forest::Train(images, 2, o);
    EXPECT_TRUE(forest.ok()) << forest.status();
    auto p = forest->Predict(images[0].depth_m, images[0].color_bgr);
    EXPECT_TRUE(p.ok());
    return cv::mean(p->probabilities[1](cv::Rect(0, 0, 40, 60)))[0];
  };
  // The left (red) half is class 1 in one image and class 0 in nine: p(1 | red) is 1/10 of the
  // red samples balanced per image (1 image's 200 of 2000), about 1/2 balanced globally.
  EXPECT_LT(Share(false), 0.3);
  EXPECT_GT(Share(true), 0.4);
}

TEST(Forest, InformationGainMatchesHandComputedValues) {
  EXPECT_NEAR(HistogramEntropy({2, 2}), std::log(2.0), 1e-12);
  EXPECT_NEAR(HistogramEntropy({4, 0}), 0.0, 1e-12);
  EXPECT_NEAR(InformationGain({2, 2}, {2, 0}, {0, 2}), std::log(2.0), 1e-12);
  EXPECT_NEAR(InformationGain({2, 2}, {1, 1}, {1, 1}), 0.0, 1e-12);
  // H(3,1) - 2/4 H(2,0) - 2/4 H(1,1) = H(3/4, 1/4) - ln2 / 2.
  const double h31 = -(0.75 * std::log(0.75) + 0.25 * std::log(0.25));
  EXPECT_NEAR(InformationGain({3, 1}, {2, 0}, {1, 1}), h31 - std::log(2.0) / 2, 1e-12);
}

// Pixels that no feature can tell apart: the root is a leaf holding the balanced distribution
// (1/2, 1/2); eq. 9 re-weights it by the prior of the full training set (9:1).
TEST(Forest, PriorReweightingFollowsEquationNine) {
  LabeledImage im;
  im.depth_m = cv::Mat(10, 10, CV_32FC1, cv::Scalar(1.0f));
  im.color_bgr = cv::Mat(10, 10, CV_8UC3, cv::Scalar(50, 60, 70));
  im.labels = cv::Mat(10, 10, CV_8UC1, cv::Scalar(0));
  im.labels(cv::Rect(0, 0, 10, 1)).setTo(1);  // 10 of 100 pixels
  TrainOptions root_only = Small();
  root_only.min_samples = 1000000;  // no split: the root is the leaf
  auto forest = Forest::Train({im}, 2, root_only);
  ASSERT_TRUE(forest.ok());
  EXPECT_NEAR(forest->class_prior()[0], 0.9, 1e-12);
  auto balanced = forest->Predict(im.depth_m, im.color_bgr, Decision::kBalanced);
  auto weighted = forest->Predict(im.depth_m, im.color_bgr, Decision::kPriorWeighted);
  ASSERT_TRUE(balanced.ok() && weighted.ok());
  EXPECT_NEAR(balanced->probabilities[1].at<float>(5, 5), 0.5f, 1e-6);
  EXPECT_NEAR(weighted->probabilities[0].at<float>(5, 5), 0.9f, 1e-6);
  EXPECT_NEAR(weighted->probabilities[1].at<float>(5, 5), 0.1f, 1e-6);
}

ModelDescription Described(std::vector<std::string> names) {
  ModelDescription d;
  d.class_names = std::move(names);
  d.class_colors = {0x102030, 0xA0B0C0};
  d.training_json = R"({"data":{"images":1}})";
  return d;
}

TEST(Forest, IsDeterministicAndRoundTripsBitExact) {
  const LabeledImage im = Halves(true);
  auto a = Forest::Train({im}, 2, Small());
  auto b = Forest::Train({im}, 2, Small());
  ASSERT_TRUE(a.ok() && b.ok());
  const std::string bytes = a->Serialize(Described({"left", "right"}));
  EXPECT_TRUE(bytes == b->Serialize(Described({"left", "right"}))) << "same seed, same forest";
  ModelDescription read;
  auto loaded = Forest::Deserialize(bytes, &read);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_EQ(read.class_names, (std::vector<std::string>{"left", "right"}));
  EXPECT_EQ(read.class_colors, (std::vector<uint32_t>{0x102030, 0xA0B0C0}));
  EXPECT_EQ(read.training_json, R"({"data":{"images":1}})");
  EXPECT_TRUE(loaded->Serialize(read) == bytes) << "bit-exact round trip";
  auto p1 = a->Predict(im.depth_m, im.color_bgr);
  auto p2 = loaded->Predict(im.depth_m, im.color_bgr);
  EXPECT_EQ(cv::countNonZero(p1->labels != p2->labels), 0);
}

uint64_t Fnv1a(const std::string& bytes) {
  uint64_t h = 1469598103934665603ULL;
  for (char c : bytes) {
    h ^= static_cast<uint8_t>(c);
    h *= 1099511628211ULL;
  }
  return h;
}

TEST(Forest, ReadsVersionOneModelFiles) {
  // A version-1 file is a version-2 file without colours and training summary.
  auto forest = Forest::Train({Halves(true)}, 2, Small());
  ASSERT_TRUE(forest.ok());
  ModelDescription d = Described({"a", "b"});
  d.training_json.clear();
  std::string v2 = forest->Serialize(d);
  const size_t names_end = 4 + 4 + 4 + 2 * 8 + 4 + (4 + 1) * 2;
  std::string v1 = v2.substr(0, names_end) + v2.substr(names_end + 2 * 4 + 4);
  v1 = v1.substr(0, v1.size() - 8);
  const uint32_t one = 1;
  std::memcpy(v1.data() + 4, &one, 4);
  const uint64_t sum = Fnv1a(v1);
  v1.append(reinterpret_cast<const char*>(&sum), 8);
  ModelDescription read;
  auto loaded = Forest::Deserialize(v1, &read);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_EQ(read.class_names, (std::vector<std::string>{"a", "b"}));
  EXPECT_EQ(read.class_colors, (std::vector<uint32_t>{DefaultClassColor(0), DefaultClassColor(1)}));
  EXPECT_EQ(loaded->node_count(), forest->node_count());
}

// Class names are listed back to clients as proto3 strings: a model whose names are not UTF-8
// text (a hand-made file with a valid checksum) is refused at upload, not listed unreadable.
TEST(Forest, AModelWhoseClassNamesAreNotUtf8IsRefused) {
  auto forest = Forest::Train({Halves(true)}, 2, Small());
  ASSERT_TRUE(forest.ok());
  const auto status =
      Forest::Deserialize(forest->Serialize(Described({"a", "b\xC3"})), nullptr).status();
  EXPECT_TRUE(absl::IsDataLoss(status)) << status;
  EXPECT_NE(status.message().find("class name"), std::string::npos) << status;
}

TEST(Forest, CorruptAndTruncatedModelsGiveClearErrors) {
  auto forest = Forest::Train({Halves(true)}, 2, Small());
  ASSERT_TRUE(forest.ok());
  const std::string bytes = forest->Serialize(Described({"a", "b"}));
  std::string flipped = bytes;
  flipped[bytes.size() / 2] ^= 0x40;
  EXPECT_TRUE(absl::IsDataLoss(Forest::Deserialize(flipped, nullptr).status()));
  EXPECT_FALSE(Forest::Deserialize(bytes.substr(0, bytes.size() - 20), nullptr).ok());
  EXPECT_TRUE(absl::IsInvalidArgument(Forest::Deserialize("not a model at all", nullptr).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(Forest::Deserialize("", nullptr).status()));
  // A version from the future: a clear "upgrade" message, not "corrupt".
  std::string future = bytes.substr(0, bytes.size() - 8);
  const uint32_t v99 = 99;
  std::memcpy(future.data() + 4, &v99, 4);
  const uint64_t sum = Fnv1a(future);
  future.append(reinterpret_cast<const char*>(&sum), 8);
  const auto status = Forest::Deserialize(future, nullptr).status();
  EXPECT_TRUE(absl::IsFailedPrecondition(status)) << status;
  EXPECT_NE(status.message().find("version 99"), std::string::npos) << status;
}

// A file's node count is checked against its size before anything is allocated (a 142-byte
// model claiming 2^26 nodes made the reader allocate 3.5 GB; found by
// tests/fuzz/forest_model_fuzz).
TEST(Forest, AModelClaimingMoreNodesThanItHoldsIsRefusedBeforeAllocating) {
  TrainOptions one_tree = Small();
  one_tree.trees = 1;
  auto forest = Forest::Train({Halves(true)}, 2, one_tree);
  ASSERT_TRUE(forest.ok());
  std::string body = forest->Serialize(Described({"a", "b"}));
  body.resize(body.size() - 8);  // without the checksum
  // The tree count (1) followed by the first tree's node count.
  const uint32_t header[2] = {1, static_cast<uint32_t>(forest->node_count())};
  const size_t at = body.find(std::string(reinterpret_cast<const char*>(header), 8));
  ASSERT_NE(at, std::string::npos);
  const uint32_t claimed = (1u << 26) - 1;
  std::memcpy(body.data() + at + 4, &claimed, 4);
  const uint64_t sum = Fnv1a(body);
  body.append(reinterpret_cast<const char*>(&sum), 8);
  const auto status = Forest::Deserialize(body, nullptr).status();
  EXPECT_TRUE(absl::IsDataLoss(status)) << status;
  EXPECT_NE(status.message().find("node count"), std::string::npos) << status;
}

TEST(Forest, RejectsBadTrainingData) {
  LabeledImage im = Halves(true);
  EXPECT_TRUE(absl::IsInvalidArgument(Forest::Train({}, 2, Small()).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(Forest::Train({im}, 1, Small()).status()));
  im.labels.at<uint8_t>(0, 0) = 7;
  auto s = Forest::Train({im}, 2, Small()).status();
  EXPECT_TRUE(absl::IsInvalidArgument(s));
  EXPECT_NE(s.message().find("label 7"), std::string::npos) << s;
  TrainOptions bad = Small();
  bad.trees = 0;
  EXPECT_TRUE(absl::IsInvalidArgument(Forest::Train({Halves(true)}, 2, bad).status()));
  auto forest = Forest::Train({Halves(true)}, 2, Small());
  EXPECT_TRUE(absl::IsInvalidArgument(
      forest->Predict(cv::Mat(10, 10, CV_16UC1), cv::Mat(10, 10, CV_8UC3)).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(
      forest->Predict(Halves(true).depth_m, Halves(true).color_bgr, Decision::kBalanced, 0)
          .status()));
}

// A 2x2 organized cloud with fields x y z rgba label: the header with the given WIDTH, SIZE,
// COUNT and DATA lines, and for ASCII its four points.
std::string PcdText(const std::string& width = "2", const std::string& size = "4 4 4 4 4",
                    const std::string& count = "1 1 1 1 1", const std::string& data = "ascii") {
  std::string out = "VERSION 0.7\nFIELDS x y z rgba label\nSIZE " + size +
                    "\nTYPE F F F U U\nCOUNT " + count + "\nWIDTH " + width +
                    "\nHEIGHT 2\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA " + data + "\n";
  if (data == "ascii") out += "0 0 1 255 1\n0.1 0 1 255 1\n0 0.1 1 255 21\n0.1 0.1 1.2 255 21\n";
  return out;
}

// Each was a crash, an out-of-bounds read or a many-gigabyte allocation inside PCL 1.13 before
// the reader checked the header (found by tests/fuzz/labeled_pcd_fuzz); each is now an
// InvalidArgument naming the file.
TEST(ReadLabeledPcd, RefusesMalformedFilesBeforePclReadsThem) {
  testing::TempDir tmp;
  const std::string path = tmp.File("cloud.pcd");
  auto read = [&](const std::string& bytes) {
    std::ofstream(path, std::ios::binary | std::ios::trunc) << bytes;
    return io::ReadLabeledPcd(path);
  };
  auto good = read(PcdText());
  ASSERT_TRUE(good.ok()) << good.status();
  EXPECT_EQ(good->frame.depth_m.size(), cv::Size(2, 2));
  EXPECT_FLOAT_EQ(good->frame.depth_m.at<float>(1, 1), 1.2f);
  EXPECT_EQ(good->labels.at<int>(1, 0), 21);
  const std::string compressed_claim =  // 8 packed bytes said to unpack to 3.4 GB
      std::string("\x08\0\0\0\0\0\0\xcd", 8) + std::string(8, '\x01');
  for (const std::string& bad : {
           std::string("DATADDA"),         // PCL threw out_of_range
           PcdText("2", "4 4 65535 4 4"),  // SIZE not its TYPE's
           PcdText("0"),                   // no points
           PcdText("2", "4 4 4 4 4", "0 1 1 1 1", "binary") + std::string(80, 'x'),  // COUNT 0
           PcdText("2", "4 4 4 4 4", "1 1 " + std::string(56, '4') + " 1 1"),        // 10^56 values
           PcdText("2", "4 4 4 4 4", "1 1 1 1 1", "binary") + "short",  // truncated body
           PcdText("2", "4 4 4 4 4", "1 1 1 1 1", "binary_compressed") + compressed_claim,
       }) {
    auto r = read(bad);
    EXPECT_TRUE(absl::IsInvalidArgument(r.status())) << bad.substr(0, 80) << ": " << r.status();
    EXPECT_NE(r.status().message().find(path), std::string::npos) << r.status();
  }
}

// Every input labeled_pcd_fuzz found (tests/fuzz/regressions/labeled_pcd_fuzz; each crashed,
// read outside a buffer or allocated gigabytes inside PCL) is refused with a status.
TEST(ReadLabeledPcd, EveryFuzzFindingIsRefused) {
  const std::filesystem::path dir =
      std::filesystem::path(LIFEMAP_SOURCE_DIR) / "tests/fuzz/regressions/labeled_pcd_fuzz";
  int files = 0;
  for (const auto& e : std::filesystem::directory_iterator(dir)) {
    auto read = io::ReadLabeledPcd(e.path().string());
    EXPECT_TRUE(absl::IsInvalidArgument(read.status())) << e.path() << ": " << read.status();
    ++files;
  }
  EXPECT_GE(files, 7);
}

// Real data: mOSD table-top scenes, table (labels 1-9) against objects (20 and above).
LabeledImage MosdImage(const std::string& path) {
  auto f = io::ReadLabeledPcd(path);
  EXPECT_TRUE(f.ok()) << f.status();
  LabeledImage im;
  im.depth_m = f->frame.depth_m;
  im.color_bgr = f->frame.color_bgr;
  im.labels = io::MosdTableObjectClasses(f->labels);
  return im;
}

TEST(Forest, SeparatesObjectsFromTheTableOnRealScenes) {
  LIFEMAP_REQUIRE_DATASET(dir, "pcl_mosd_labeled_subset");
  std::vector<LabeledImage> train;
  for (const char* name : {"learn0", "learn8", "learn17", "learn25", "learn33", "learn44"}) {
    train.push_back(MosdImage(dir + "/learn/" + name + ".pcd"));
  }
  TrainOptions o;
  o.trees = 2;
  o.max_depth = 12;
  o.pixels_per_image = 1000;
  o.candidates = 200;
  auto forest = Forest::Train(train, 2, o);
  ASSERT_TRUE(forest.ok()) << forest.status();
  for (const char* name : {"test5", "test31"}) {
    const LabeledImage test = MosdImage(dir + "/test/" + name + ".pcd");
    const cv::Mat scored = (test.labels != kIgnore) & (test.depth_m > 0);
    auto p = forest->Predict(test.depth_m, test.color_bgr, Decision::kBalanced, 2);
    ASSERT_TRUE(p.ok());
    const double accuracy = cv::countNonZero((p->labels == test.labels) & scored) /
                            static_cast<double>(cv::countNonZero(scored));
    EXPECT_GT(accuracy, 0.8) << name;
  }
}

}  // namespace
}  // namespace lifemap::forest

#include "core/forest/labeled_data.h"

#include <filesystem>
#include <fstream>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "tests/testing/test_util.h"

namespace lifemap::forest {
namespace {

namespace fs = std::filesystem;

// A TUM folder of 3 synthetic frames with label PNGs: left half class 0, right half class 1,
// one unlabelled column (255).
void WriteLabelPngFolder(const std::string& dir, const std::vector<std::string>& classes) {
  testing::WriteSyntheticTum(dir, 3, 0.02, 64, 48);
  fs::create_directories(dir + "/labels");
  std::ofstream names(dir + "/labels/classes.txt");
  names << "# one class per line\n";
  for (const auto& c : classes) names << c << "\n";
  for (const auto& e : fs::directory_iterator(dir + "/rgb")) {
    cv::Mat labels(48, 64, CV_8UC1, cv::Scalar(0));
    labels(cv::Rect(32, 0, 32, 48)).setTo(1);
    labels.col(31).setTo(255);
    cv::imwrite(dir + "/labels/" + e.path().stem().string() + ".png", labels);
  }
}

TEST(LabeledData, ReadsLabelPngFolders) {
  testing::TempDir tmp;
  WriteLabelPngFolder(tmp.File("a"), {"floor", "thing"});
  WriteLabelPngFolder(tmp.File("b"), {"floor", "thing"});
  LabeledDataOptions o;
  o.frame_stride = 2;
  auto data = ReadLabeledData({tmp.File("a"), tmp.File("b")}, o);
  ASSERT_TRUE(data.ok()) << data.status();
  EXPECT_EQ(data->kind, "label-png");
  EXPECT_EQ(data->class_names, (std::vector<std::string>{"floor", "thing"}));
  ASSERT_EQ(data->images.size(), 4u) << "frames 0 and 2 of each folder";
  const auto& im = data->images[0];
  EXPECT_EQ(im.labels.at<uint8_t>(10, 5), 0);
  EXPECT_EQ(im.labels.at<uint8_t>(10, 40), 1);
  EXPECT_EQ(im.labels.at<uint8_t>(10, 31), kIgnore);
  EXPECT_NEAR(im.depth_m.at<float>(10, 10), 1.0f, 1e-3) << "frame 0 at 1 m; TUM scale 5000";
}

TEST(LabeledData, BadLabelsAndMixedClassesAreClearErrors) {
  testing::TempDir tmp;
  WriteLabelPngFolder(tmp.File("a"), {"floor", "thing"});
  WriteLabelPngFolder(tmp.File("c"), {"floor", "chair", "thing"});
  auto mixed = ReadLabeledData({tmp.File("a"), tmp.File("c")});
  EXPECT_TRUE(absl::IsInvalidArgument(mixed.status())) << mixed.status();
  EXPECT_NE(mixed.status().message().find("same classes"), std::string::npos) << mixed.status();

  // A label value no class names.
  WriteLabelPngFolder(tmp.File("d"), {"floor", "thing"});
  const std::string first = fs::directory_iterator(tmp.File("d/labels"))->path().string();
  for (const auto& e : fs::directory_iterator(tmp.File("d/labels"))) {
    if (e.path().extension() != ".png") continue;
    cv::Mat l = cv::imread(e.path().string(), cv::IMREAD_UNCHANGED);
    l.at<uint8_t>(7, 9) = 7;
    cv::imwrite(e.path().string(), l);
  }
  auto bad = ReadLabeledData({tmp.File("d")});
  EXPECT_TRUE(absl::IsInvalidArgument(bad.status())) << bad.status();
  EXPECT_NE(bad.status().message().find("label 7 at (9, 7)"), std::string::npos) << bad.status();

  // A missing label image names the file.
  WriteLabelPngFolder(tmp.File("e"), {"floor", "thing"});
  for (const auto& e : fs::directory_iterator(tmp.File("e/labels"))) {
    if (e.path().extension() == ".png") {
      fs::remove(e.path());
      break;
    }
  }
  auto missing = ReadLabeledData({tmp.File("e")}, LabeledDataOptions{1, SimClasses::kGrouped});
  EXPECT_TRUE(absl::IsNotFound(missing.status())) << missing.status();

  // A folder of nothing labelled says what was expected.
  fs::create_directories(tmp.File("empty"));
  auto empty = ReadLabeledData({tmp.File("empty")});
  EXPECT_TRUE(absl::IsNotFound(empty.status()));
  EXPECT_NE(empty.status().message().find("classes.txt"), std::string::npos) << empty.status();
  EXPECT_TRUE(absl::IsNotFound(ReadLabeledData({tmp.File("nowhere")}).status()));
}

// Labels are PNG only: a label file in another format (here a JPEG named .png) is refused by
// name, never handed to another decoder (found by tests/fuzz/label_png_fuzz: cv::imread decoded
// any format, JPEG 2000 and TIFF included).
TEST(LabeledData, ALabelFileThatIsNotAPngIsRefusedByName) {
  testing::TempDir tmp;
  WriteLabelPngFolder(tmp.File("a"), {"floor", "thing"});
  std::string renamed;
  for (const auto& e : fs::directory_iterator(tmp.File("a/labels"))) {
    if (e.path().extension() != ".png") continue;
    std::vector<uchar> jpeg;
    cv::imencode(".jpg", cv::Mat(48, 64, CV_8UC1, cv::Scalar(1)), jpeg);
    std::ofstream(e.path(), std::ios::binary | std::ios::trunc)
        .write(reinterpret_cast<const char*>(jpeg.data()),
               static_cast<std::streamsize>(jpeg.size()));
    renamed = e.path().string();
    break;
  }
  auto read = ReadLabeledData({tmp.File("a")});
  EXPECT_TRUE(absl::IsInvalidArgument(read.status())) << read.status();
  EXPECT_NE(read.status().message().find(renamed + ": not a readable PNG"), std::string::npos)
      << read.status();
}

TEST(LabeledData, ReadsMosdFolders) {
  LIFEMAP_REQUIRE_DATASET(dir, "pcl_mosd_labeled_subset");
  auto data = ReadLabeledData({dir + "/test"});
  ASSERT_TRUE(data.ok()) << data.status();
  EXPECT_EQ(data->kind, "mosd");
  EXPECT_EQ(data->class_names, (std::vector<std::string>{"table", "object"}));
  EXPECT_GE(data->images.size(), 5u);
  EXPECT_EQ(data->images[0].labels.type(), CV_8UC1);
}

}  // namespace
}  // namespace lifemap::forest

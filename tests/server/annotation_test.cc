// Annotations (issue 38): stored, validated, projected into a view; the training folder's tar.
#include <cstdio>
#include <fstream>

#include <gtest/gtest.h>

#include "server/engine/annotation_export.h"
#include "server/http/tar_writer.h"
#include "server/store/store.h"
#include "tests/testing/test_util.h"

namespace lifemap::server {
namespace {

store::AnnotationRecord Box(const std::string& cls, double x0, double y0, double z0, double x1,
                            double y1, double z1) {
  store::AnnotationRecord a;
  a.class_name = cls;
  store::AnnotationBox b;
  b.min[0] = x0, b.min[1] = y0, b.min[2] = z0;
  b.max[0] = x1, b.max[1] = y1, b.max[2] = z1;
  a.boxes.push_back(b);
  return a;
}

// A camera at the origin looking along +z at a wall 2 m away: 64 × 48 pixels, f = 64.
RgbdFrame Wall() {
  RgbdFrame f;
  f.intrinsics = {64, 64, 31.5, 23.5, 64, 48};
  f.depth_m = cv::Mat(48, 64, CV_32FC1, cv::Scalar(2.0f));
  f.depth_m(cv::Rect(0, 0, 4, 48)).setTo(0.0f);  // no reading along the left edge
  return f;
}

TEST(Annotations, AreStoredListedDeletedAndGoWithTheirMap) {
  testing::TempDir tmp;
  auto store = store::Store::Open(tmp.File("lifemap.db"));
  ASSERT_TRUE(store.ok()) << store.status();
  auto map = (*store)->CreateMap("m", "", 1.0);
  ASSERT_TRUE(map.ok());
  auto a = Box("chair", 0, 0, 0, 1, 2, 3);
  a.map_id = map->id;
  a.author = "op";
  a.boxes.push_back(a.boxes[0]);
  a.boxes[1].max[2] = 4.5;
  auto stored = (*store)->InsertAnnotation(a);
  ASSERT_TRUE(stored.ok()) << stored.status();
  auto listed = (*store)->ListAnnotations(map->id);
  ASSERT_TRUE(listed.ok());
  ASSERT_EQ(listed->size(), 1u);
  EXPECT_EQ((*listed)[0].id, stored->id);
  EXPECT_EQ((*listed)[0].class_name, "chair");
  EXPECT_EQ((*listed)[0].author, "op");
  ASSERT_EQ((*listed)[0].boxes.size(), 2u);
  // Every coordinate as given (the packed bytes once dangled and lost the first ones).
  for (int b = 0; b < 2; ++b) {
    for (int d = 0; d < 3; ++d) {
      EXPECT_EQ((*listed)[0].boxes[b].min[d], 0.0) << b << " " << d;
      EXPECT_EQ((*listed)[0].boxes[b].max[d], d == 2 ? (b == 0 ? 3.0 : 4.5) : d + 1.0);
    }
  }
  a.map_id = map->id + 100;
  EXPECT_TRUE(absl::IsNotFound((*store)->InsertAnnotation(a).status()));
  EXPECT_TRUE(absl::IsNotFound((*store)->DeleteAnnotation(map->id, stored->id + 1)));
  ASSERT_TRUE((*store)->DeleteAnnotation(map->id, stored->id).ok());
  EXPECT_TRUE((*store)->ListAnnotations(map->id)->empty());
  // A map's annotations are deleted with it.
  a.map_id = map->id;
  ASSERT_TRUE((*store)->InsertAnnotation(a).ok());
  ASSERT_TRUE((*store)->DeleteMap("m").ok());
  EXPECT_TRUE((*store)->ListAnnotations(map->id)->empty());
}

TEST(Annotations, BadOnesAreRefusedSayingWhy) {
  EXPECT_TRUE(ValidateAnnotation(Box("chair", 0, 0, 0, 1, 1, 1)).ok());
  auto expect_refused = [](const store::AnnotationRecord& a, const std::string& says) {
    const absl::Status s = ValidateAnnotation(a);
    EXPECT_TRUE(absl::IsInvalidArgument(s)) << s;
    EXPECT_NE(std::string(s.message()).find(says), std::string::npos) << s.message();
  };
  expect_refused(Box("", 0, 0, 0, 1, 1, 1), "1-64 characters");
  expect_refused(Box("a/b", 0, 0, 0, 1, 1, 1), "without '/'");
  expect_refused(Box("chair", 0, 2, 0, 1, 1, 1), "min exceeds its max along y");
  expect_refused(Box("chair", 0, 0, 0, 1, 1, std::nan("")), "not finite");
  expect_refused(Box("chair", 0, 0, 0, 1, 1, 5000), "beyond");
  auto none = Box("chair", 0, 0, 0, 1, 1, 1);
  none.boxes.clear();
  expect_refused(none, "at least one box");
}

TEST(Annotations, ProjectIntoTheViewsThatSeeThemAndTheLatestWins) {
  const RgbdFrame wall = Wall();
  // The wall's middle: x in [-0.5, 0.5] m at 2 m is u in [15.5, 47.5]; y in [-0.25, 0.25] is
  // v in [15.5, 31.5].
  std::vector<store::AnnotationRecord> annotations = {
      Box("poster", -0.5, -0.25, 1.9, 0.5, 0.25, 2.1),
      Box("frame", 0.0, -0.25, 1.9, 0.5, 0.25, 2.1),  // later: wins on its half
      Box("poster", 5, 5, 5, 6, 6, 6)};               // seen by no pixel
  const auto classes = AnnotationClasses(annotations);
  ASSERT_EQ(classes, (std::vector<std::string>{"background", "poster", "frame"}));
  int64_t labelled = 0;
  const cv::Mat labels = ProjectAnnotations(annotations, classes, wall, Pose{}, 0.0, &labelled);
  EXPECT_EQ(labels.at<uint8_t>(24, 20), 1);   // poster
  EXPECT_EQ(labels.at<uint8_t>(24, 40), 2);   // frame
  EXPECT_EQ(labels.at<uint8_t>(5, 20), 255);  // above the boxes
  EXPECT_EQ(labels.at<uint8_t>(24, 50), 255);
  EXPECT_EQ(labelled, 32 * 16);
  EXPECT_EQ(cv::countNonZero(labels != 255), labelled);
  // Moved 1 m to the right the camera sees the boxes 1 m further left; a margin grows them.
  Pose moved;
  moved.translation = {1.0, 0, 0};
  const cv::Mat shifted = ProjectAnnotations(annotations, classes, wall, moved, 0.0, &labelled);
  EXPECT_EQ(shifted.at<uint8_t>(24, 10), 2);    // x = -0.67 + 1 = 0.33: the frame
  EXPECT_EQ(shifted.at<uint8_t>(24, 40), 255);  // x = 1.25: none
  const cv::Mat wider = ProjectAnnotations(annotations, classes, wall, Pose{}, 0.1, &labelled);
  EXPECT_EQ(wider.at<uint8_t>(24, 48), 2);  // x = 0.52: within the 0.1 m margin
  // Beyond the depth the boxes hold nothing (a box behind the wall labels no pixel).
  const cv::Mat behind = ProjectAnnotations({Box("x", -1, -1, 2.5, 1, 1, 3)}, {"background", "x"},
                                            wall, Pose{}, 0.0, &labelled);
  EXPECT_EQ(labelled, 0);
  EXPECT_EQ(cv::countNonZero(behind != 255), 0);
}

TEST(Annotations, ManyVoxelSizedBoxesProjectAsOneBigBox) {
  // A selection of voxels covering the same region as one box labels the same pixels.
  const RgbdFrame wall = Wall();
  store::AnnotationRecord voxels;
  voxels.class_name = "poster";
  for (double x = -0.5; x < 0.5 - 1e-9; x += 0.05) {
    for (double y = -0.25; y < 0.25 - 1e-9; y += 0.05) {
      store::AnnotationBox b;
      b.min[0] = x, b.min[1] = y, b.min[2] = 1.95;
      b.max[0] = x + 0.05, b.max[1] = y + 0.05, b.max[2] = 2.05;
      voxels.boxes.push_back(b);
    }
  }
  int64_t a = 0, b = 0;
  const std::vector<std::string> classes = {"background", "poster"};
  const cv::Mat from_voxels = ProjectAnnotations({voxels}, classes, wall, Pose{}, 0.0, &a);
  const cv::Mat from_box = ProjectAnnotations({Box("poster", -0.5, -0.25, 1.95, 0.5, 0.25, 2.05)},
                                              classes, wall, Pose{}, 0.0, &b);
  EXPECT_EQ(a, b);
  EXPECT_EQ(cv::countNonZero(from_voxels != from_box), 0);
}

TEST(TarWriter, WritesAnArchiveTarReads) {
  testing::TempDir tmp;
  web::TarWriter tar;
  ASSERT_TRUE(tar.Add("f/labels/classes.txt", "background\nchair\n", 1.7e9).ok());
  // A path beyond 100 bytes is split at a '/' (ustar's prefix field).
  const std::string deep = "f/" + std::string(120, 'a') + "/rgb.png";
  ASSERT_TRUE(tar.Add(deep, std::string(1000, 'x'), 0).ok());
  EXPECT_TRUE(absl::IsInvalidArgument(tar.Add(std::string(300, 'b'), "", 0)));
  EXPECT_TRUE(absl::IsInvalidArgument(tar.Add("", "", 0)));
  const std::string bytes = tar.Finish();
  EXPECT_EQ(bytes.size() % 512, 0u);
  const std::string path = tmp.File("t.tar");
  std::ofstream(path, std::ios::binary) << bytes;
  const std::string listing = tmp.File("list.txt");
  ASSERT_EQ(std::system(("tar -tvf " + path + " > " + listing).c_str()), 0);
  std::ifstream in(listing);
  std::string all((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  EXPECT_NE(all.find("f/labels/classes.txt"), std::string::npos) << all;
  EXPECT_NE(all.find(deep), std::string::npos) << all;
  EXPECT_NE(all.find(" 1000 "), std::string::npos) << all;
}

}  // namespace
}  // namespace lifemap::server

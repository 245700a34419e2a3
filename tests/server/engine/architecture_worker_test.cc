#include "server/engine/architecture.h"

#include <gtest/gtest.h>

#include <opencv2/core.hpp>

#include "server/store/store.h"
#include "tests/testing/test_util.h"

namespace lifemap::server {
namespace {

// A key frame queued with a pose from before its visit's frame changed (an anchor moved the
// visit into its map's frame, and the plan was rebuilt there) is not folded into the plan: the
// plan never mixes two frames (issue 54). Key frames posed in the new frame are folded.
TEST(ArchitectureWorker, AKeyFramePosedBeforeTheVisitsFrameChangedIsNotFolded) {
  testing::TempDir tmp;
  auto store = store::Store::Open(tmp.File("lifemap.db"));
  ASSERT_TRUE(store.ok()) << store.status();
  ASSERT_TRUE((*store)->CreateMap("m", "", 1.0).ok());
  auto visit = (*store)->StartVisit("m", "", "", 1.0);
  ASSERT_TRUE(visit.ok()) << visit.status();
  PlaceIndex index(store->get());
  VisitArchitecture arch;
  auto job = [&](uint64_t generation) {
    return ArchitectureWorker::Visit{visit->id, visit->map_id, [] { return std::string("m"); },
                                     &arch,     nullptr,       generation};
  };
  const CameraIntrinsics k{525, 525, 159.5, 119.5, 320, 240};
  const cv::Mat wall(240, 320, CV_32FC1, cv::Scalar(2.0f));  // a wall 2 m ahead
  ArchitectureWorker worker(store->get(), &index);
  worker.Wait(worker.Submit(job(0), wall, k, Pose{}));
  EXPECT_EQ(arch.builder.keyframes(), 1);
  // The anchor: generation 1, rebuilt from the store (which holds none of these key frames).
  worker.Wait(worker.SubmitRebuild(job(1)));
  EXPECT_EQ(arch.builder.keyframes(), 0);
  worker.Wait(worker.Submit(job(0), wall, k, Pose{}));  // queued before the anchor
  EXPECT_EQ(arch.builder.keyframes(), 0);
  EXPECT_EQ(arch.stale_key_frames, 1);
  worker.Wait(worker.Submit(job(1), wall, k, Pose{}));
  EXPECT_EQ(arch.builder.keyframes(), 1);
  EXPECT_EQ(arch.stale_key_frames, 1);
}

}  // namespace
}  // namespace lifemap::server

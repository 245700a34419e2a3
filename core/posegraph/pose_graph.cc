#include "core/posegraph/pose_graph.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <memory>

#include <ceres/ceres.h>

#include "absl/strings/str_cat.h"

namespace lifemap::posegraph {
namespace {

// One node's parameters as Ceres sees them: translation, and a unit quaternion in Eigen's
// storage order (x, y, z, w) on Ceres' EigenQuaternionManifold.
struct NodeParams {
  double t[3];
  double q[4];
};

// The residual of a relative-pose measurement, whitened: the translation of b in a's frame minus
// the measured one (metres / sigma_m), and twice the vector part of the rotation error quaternion
// (about the rotation angle, radians / sigma_rad). Zero when the poses agree with the
// measurement. Templated for Ceres' automatic differentiation.
class RelativePoseError {
 public:
  RelativePoseError(const Pose& measured, double sigma_m, double sigma_rad)
      : t_ab_(measured.translation),
        q_ab_(measured.rotation),
        inv_sigma_m_(1.0 / sigma_m),
        inv_sigma_rad_(1.0 / sigma_rad) {}

  template <typename T>
  bool operator()(const T* t_a, const T* q_a, const T* t_b, const T* q_b, T* residual) const {
    const Eigen::Map<const Eigen::Matrix<T, 3, 1>> pa(t_a), pb(t_b);
    const Eigen::Map<const Eigen::Quaternion<T>> qa(q_a), qb(q_b);
    const Eigen::Quaternion<T> qa_inv = qa.conjugate();
    const Eigen::Matrix<T, 3, 1> t_ab_est = qa_inv * (pb - pa);
    const Eigen::Quaternion<T> q_ab_est = qa_inv * qb;
    const Eigen::Quaternion<T> dq = q_ab_.template cast<T>() * q_ab_est.conjugate();
    Eigen::Map<Eigen::Matrix<T, 6, 1>> r(residual);
    r.template head<3>() = (t_ab_est - t_ab_.template cast<T>()) * T(inv_sigma_m_);
    // The sign of a quaternion is arbitrary: take the error's short way round.
    const T sign = dq.w() < T(0) ? T(-1) : T(1);
    r.template tail<3>() = dq.vec() * (T(2) * sign * T(inv_sigma_rad_));
    return true;
  }

 private:
  const Eigen::Vector3d t_ab_;
  const Eigen::Quaterniond q_ab_;
  const double inv_sigma_m_;
  const double inv_sigma_rad_;
};

bool Finite(const Pose& p) {
  return p.translation.allFinite() && p.rotation.coeffs().allFinite() &&
         std::abs(p.rotation.norm() - 1.0) < 1e-3;
}

}  // namespace

const char* EdgeKindName(EdgeKind kind) {
  switch (kind) {
    case EdgeKind::kOdometry:
      return "odometry";
    case EdgeKind::kLoop:
      return "loop";
    case EdgeKind::kAnchor:
      return "anchor";
  }
  return "unknown";
}

absl::Status OptimiseOptions::Validate() const {
  if (max_iterations < 1 || max_iterations > 1000) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_iterations must be within [1, 1000], got ", max_iterations));
  }
  if (!(robust_scale > 0) || !std::isfinite(robust_scale)) {
    return absl::InvalidArgumentError(absl::StrCat("robust_scale must be > 0, got ", robust_scale));
  }
  if (!(outlier_chi2 > 0) || !std::isfinite(outlier_chi2)) {
    return absl::InvalidArgumentError(absl::StrCat("outlier_chi2 must be > 0, got ", outlier_chi2));
  }
  if (!(odometry_robust_scale >= 0) || !std::isfinite(odometry_robust_scale)) {
    return absl::InvalidArgumentError(
        absl::StrCat("odometry_robust_scale must be >= 0, got ", odometry_robust_scale));
  }
  if (max_rejection_rounds < 0 || max_rejection_rounds > 10) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_rejection_rounds must be within [0, 10], got ", max_rejection_rounds));
  }
  if (threads < 1 || threads > 64) {
    return absl::InvalidArgumentError(
        absl::StrCat("threads must be within [1, 64], got ", threads));
  }
  return absl::OkStatus();
}

Pose Relative(const Pose& a, const Pose& b) {
  Pose r;
  const Eigen::Quaterniond a_inv = a.rotation.conjugate();
  r.translation = a_inv * (b.translation - a.translation);
  r.rotation = (a_inv * b.rotation).normalized();
  return r;
}

double EdgeChi2(const Edge& edge, const Pose& a, const Pose& b) {
  const RelativePoseError error(edge.T_from_to, edge.sigma_m, edge.sigma_rad);
  const double qa[4] = {a.rotation.x(), a.rotation.y(), a.rotation.z(), a.rotation.w()};
  const double qb[4] = {b.rotation.x(), b.rotation.y(), b.rotation.z(), b.rotation.w()};
  double r[6];
  error(a.translation.data(), qa, b.translation.data(), qb, r);
  double chi2 = 0;
  for (double v : r) chi2 += v * v;
  return chi2;
}

absl::StatusOr<OptimiseResult> Optimise(const std::map<int64_t, Pose>& initial,
                                        const std::vector<Edge>& edges,
                                        const std::set<int64_t>& fixed,
                                        const OptimiseOptions& options) {
  if (auto s = options.Validate(); !s.ok()) return s;
  for (const auto& [id, pose] : initial) {
    if (!Finite(pose)) {
      return absl::InvalidArgumentError(absl::StrCat("node ", id, " has a non-finite pose"));
    }
  }
  for (size_t i = 0; i < edges.size(); ++i) {
    const Edge& e = edges[i];
    if (!initial.count(e.from) || !initial.count(e.to)) {
      return absl::InvalidArgumentError(absl::StrCat("edge ", i, " (", EdgeKindName(e.kind), " ",
                                                     e.from, " -> ", e.to,
                                                     ") names a node that is not in the graph"));
    }
    if (e.from == e.to) {
      return absl::InvalidArgumentError(
          absl::StrCat("edge ", i, " joins node ", e.from, " to itself"));
    }
    if (!Finite(e.T_from_to)) {
      return absl::InvalidArgumentError(absl::StrCat("edge ", i, " has a non-finite measurement"));
    }
    if (!(e.sigma_m > 0) || !(e.sigma_rad > 0) || !std::isfinite(e.sigma_m) ||
        !std::isfinite(e.sigma_rad)) {
      return absl::InvalidArgumentError(absl::StrCat("edge ", i, " needs positive sigmas, got ",
                                                     e.sigma_m, " m and ", e.sigma_rad, " rad"));
    }
  }
  for (int64_t id : fixed) {
    if (!initial.count(id)) {
      return absl::InvalidArgumentError(absl::StrCat("fixed node ", id, " is not in the graph"));
    }
  }
  OptimiseResult result;
  result.poses = initial;
  result.converged = true;
  if (initial.empty() || edges.empty()) return result;

  std::map<int64_t, NodeParams> params;
  for (const auto& [id, pose] : initial) {
    NodeParams& p = params[id];
    std::copy(pose.translation.data(), pose.translation.data() + 3, p.t);
    const Eigen::Quaterniond q = pose.rotation.normalized();
    p.q[0] = q.x();
    p.q[1] = q.y();
    p.q[2] = q.z();
    p.q[3] = q.w();
  }
  std::vector<bool> active(edges.size(), true);
  const auto start = std::chrono::steady_clock::now();
  for (int round = 0;; ++round) {
    ceres::Problem::Options problem_options;
    // The manifold and losses are shared between blocks: the problem must not delete them.
    problem_options.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
    problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
    ceres::Problem problem(problem_options);
    ceres::EigenQuaternionManifold quaternion;
    ceres::CauchyLoss robust(options.robust_scale);
    ceres::CauchyLoss robust_odometry(
        options.odometry_robust_scale > 0 ? options.odometry_robust_scale : 1.0);
    ceres::LossFunction* odometry_loss =
        options.odometry_robust_scale > 0 ? &robust_odometry : nullptr;
    for (size_t i = 0; i < edges.size(); ++i) {
      if (!active[i]) continue;
      const Edge& e = edges[i];
      auto* cost = new ceres::AutoDiffCostFunction<RelativePoseError, 6, 3, 4, 3, 4>(
          new RelativePoseError(e.T_from_to, e.sigma_m, e.sigma_rad));
      NodeParams& a = params[e.from];
      NodeParams& b = params[e.to];
      problem.AddResidualBlock(cost, e.kind == EdgeKind::kOdometry ? odometry_loss : &robust, a.t,
                               a.q, b.t, b.q);
      problem.SetManifold(a.q, &quaternion);
      problem.SetManifold(b.q, &quaternion);
    }
    // The gauge: fixed nodes (or the first one) do not move.
    bool any_fixed = false;
    for (auto& [id, p] : params) {
      if (!problem.HasParameterBlock(p.t)) continue;
      if (fixed.count(id) || (fixed.empty() && !any_fixed)) {
        problem.SetParameterBlockConstant(p.t);
        problem.SetParameterBlockConstant(p.q);
        any_fixed = true;
      }
    }
    ceres::Solver::Options solver;
    solver.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
    solver.max_num_iterations = options.max_iterations;
    solver.num_threads = options.threads;
    solver.logging_type = ceres::SILENT;
    ceres::Solver::Summary summary;
    ceres::Solve(solver, &problem, &summary);
    if (round == 0) result.initial_cost = summary.initial_cost;
    result.final_cost = summary.final_cost;
    result.iterations += static_cast<int>(summary.iterations.size());
    ++result.solves;
    result.converged = summary.termination_type == ceres::CONVERGENCE;
    result.report = summary.BriefReport();
    if (!summary.IsSolutionUsable()) {
      return absl::InternalError(
          absl::StrCat("the pose graph could not be solved: ", summary.message));
    }
    if (round >= options.max_rejection_rounds) break;
    // Robust edges the solution still disagrees with are switched off, the worst first; the
    // graph is solved again without them.
    std::vector<std::pair<double, size_t>> outliers;
    for (size_t i = 0; i < edges.size(); ++i) {
      const Edge& e = edges[i];
      if (!active[i] || e.kind == EdgeKind::kOdometry) continue;
      const NodeParams& a = params[e.from];
      const NodeParams& b = params[e.to];
      Pose pa, pb;
      pa.translation = Eigen::Vector3d(a.t[0], a.t[1], a.t[2]);
      pa.rotation = Eigen::Quaterniond(a.q[3], a.q[0], a.q[1], a.q[2]).normalized();
      pb.translation = Eigen::Vector3d(b.t[0], b.t[1], b.t[2]);
      pb.rotation = Eigen::Quaterniond(b.q[3], b.q[0], b.q[1], b.q[2]).normalized();
      const double chi2 = EdgeChi2(e, pa, pb);
      if (chi2 > options.outlier_chi2) outliers.push_back({chi2, i});
    }
    if (outliers.empty()) break;
    // Only the worst one per round: one wrong loop can make right ones look wrong until it is
    // gone.
    const auto worst = std::max_element(outliers.begin(), outliers.end());
    active[worst->second] = false;
    result.rejected.push_back(worst->second);
  }
  result.solve_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  for (auto& [id, pose] : result.poses) {
    const NodeParams& p = params[id];
    Pose out;
    out.translation = Eigen::Vector3d(p.t[0], p.t[1], p.t[2]);
    out.rotation = Eigen::Quaterniond(p.q[3], p.q[0], p.q[1], p.q[2]).normalized();
    result.max_correction_m =
        std::max(result.max_correction_m, (out.translation - pose.translation).norm());
    pose = out;
  }
  return result;
}

}  // namespace lifemap::posegraph

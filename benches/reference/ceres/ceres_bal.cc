// Ceres reference driver for BAL bundle adjustment, timed like `factord ba`.
//
//   ceres_bal <problem.txt> [--linear-solver dense_schur|sparse_schur] [--max-iterations N]
//             [--huber SCALE] [--function-tolerance T] [--threads N]
//
// Prints one JSON object: initial/final cost (½Σ‖r‖², Ceres' convention), iterations (successful
// and unsuccessful), solve seconds (Ceres' total time minus nothing: the Solve call), termination.
// Model: Snavely camera (angle-axis, t, f, k1, k2), p = −P/P.z, as in the BAL documentation;
// automatic differentiation, one thread unless --threads (Ceres' num_threads: evaluation and the
// Schur eliminator), LM (Ceres' default trust region), points eliminated first.
#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

namespace {

struct Bal {
  int num_cameras = 0, num_points = 0, num_observations = 0;
  std::vector<int> camera_index, point_index;
  std::vector<double> observations, parameters;  // parameters: cameras (9 each) then points (3 each)
  double* camera(int i) { return parameters.data() + 9 * i; }
  double* point(int j) { return parameters.data() + 9 * num_cameras + 3 * j; }
};

bool Load(const char* path, Bal* bal) {
  std::ifstream in(path);
  if (!(in >> bal->num_cameras >> bal->num_points >> bal->num_observations)) return false;
  bal->camera_index.resize(bal->num_observations);
  bal->point_index.resize(bal->num_observations);
  bal->observations.resize(2 * bal->num_observations);
  for (int k = 0; k < bal->num_observations; ++k) {
    if (!(in >> bal->camera_index[k] >> bal->point_index[k] >> bal->observations[2 * k] >>
          bal->observations[2 * k + 1]))
      return false;
  }
  bal->parameters.resize(9 * bal->num_cameras + 3 * bal->num_points);
  for (double& v : bal->parameters) {
    if (!(in >> v)) return false;
  }
  return true;
}

// Residual = predicted − observed pixel for the BAL camera model.
struct Reprojection {
  Reprojection(double x, double y) : x(x), y(y) {}
  template <typename T>
  bool operator()(const T* const camera, const T* const point, T* residual) const {
    T p[3];
    ceres::AngleAxisRotatePoint(camera, point, p);
    for (int i = 0; i < 3; ++i) p[i] += camera[3 + i];
    const T px = -p[0] / p[2];
    const T py = -p[1] / p[2];
    const T n = px * px + py * py;
    const T r = T(1.0) + camera[7] * n + camera[8] * n * n;
    residual[0] = camera[6] * r * px - T(x);
    residual[1] = camera[6] * r * py - T(y);
    return true;
  }
  double x, y;
};

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: %s <problem.txt> [--linear-solver dense_schur|sparse_schur|iterative_schur] "
                         "[--max-iterations N] [--huber SCALE] [--function-tolerance T] [--threads N]\n",
                 argv[0]);
    return 2;
  }
  std::string solver = "dense_schur";
  int max_iterations = 100, threads = 1;
  double huber = 0.0, function_tolerance = 1e-6;
  for (int i = 2; i + 1 < argc; i += 2) {
    if (!std::strcmp(argv[i], "--linear-solver")) solver = argv[i + 1];
    else if (!std::strcmp(argv[i], "--max-iterations")) max_iterations = std::atoi(argv[i + 1]);
    else if (!std::strcmp(argv[i], "--huber")) huber = std::atof(argv[i + 1]);
    else if (!std::strcmp(argv[i], "--function-tolerance")) function_tolerance = std::atof(argv[i + 1]);
    else if (!std::strcmp(argv[i], "--threads")) threads = std::atoi(argv[i + 1]);
    else { std::fprintf(stderr, "unknown option %s\n", argv[i]); return 2; }
  }
  Bal bal;
  if (!Load(argv[1], &bal)) { std::fprintf(stderr, "cannot read %s\n", argv[1]); return 2; }

  ceres::Problem problem;
  for (int k = 0; k < bal.num_observations; ++k) {
    auto* cost = new ceres::AutoDiffCostFunction<Reprojection, 2, 9, 3>(
        new Reprojection(bal.observations[2 * k], bal.observations[2 * k + 1]));
    ceres::LossFunction* loss = huber > 0 ? new ceres::HuberLoss(huber) : nullptr;
    problem.AddResidualBlock(cost, loss, bal.camera(bal.camera_index[k]), bal.point(bal.point_index[k]));
  }
  ceres::Solver::Options options;
  if (solver == "iterative_schur") {
    // Implicit Schur complement and conjugate gradients, preconditioned by the block diagonal
    // of S (one block per camera): the solver for problems whose S does not fit in memory.
    options.linear_solver_type = ceres::ITERATIVE_SCHUR;
    options.preconditioner_type = ceres::SCHUR_JACOBI;
  } else if (solver == "sparse_schur") {
    options.linear_solver_type = ceres::SPARSE_SCHUR;
  } else if (solver == "dense_schur") {
    options.linear_solver_type = ceres::DENSE_SCHUR;
  } else {
    std::fprintf(stderr, "unknown linear solver %s\n", solver.c_str());
    return 2;
  }
  options.num_threads = threads;
  options.max_num_iterations = max_iterations;
  options.function_tolerance = function_tolerance;
  options.minimizer_progress_to_stdout = false;
  options.logging_type = ceres::SILENT;
  // Points first (group 0), cameras second: the Schur complement eliminates the points.
  auto* ordering = new ceres::ParameterBlockOrdering;
  for (int j = 0; j < bal.num_points; ++j) ordering->AddElementToGroup(bal.point(j), 0);
  for (int i = 0; i < bal.num_cameras; ++i) ordering->AddElementToGroup(bal.camera(i), 1);
  options.linear_solver_ordering.reset(ordering);

  ceres::Solver::Summary summary;
  auto start = std::chrono::steady_clock::now();
  ceres::Solve(options, &problem, &summary);
  double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf(
      "{\"linear_solver\": \"%s\", \"threads\": %d, \"initial_cost\": %.10g, \"final_cost\": %.10g, "
      "\"iterations\": %d, \"successful_steps\": %d, \"unsuccessful_steps\": %d, "
      "\"solve_seconds\": %.6f, \"ceres_total_seconds\": %.6f, \"termination\": \"%s\", "
      "\"converged\": %s}\n",
      solver.c_str(), threads, summary.initial_cost, summary.final_cost,
      summary.num_successful_steps + summary.num_unsuccessful_steps, summary.num_successful_steps,
      summary.num_unsuccessful_steps, wall, summary.total_time_in_seconds,
      ceres::TerminationTypeToString(summary.termination_type),
      summary.termination_type == ceres::CONVERGENCE ? "true" : "false");
  return 0;
}

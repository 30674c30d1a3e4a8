// ceres_pose_graph — reference Ceres Solver driver for factord's pose-graph benchmarks.
//
// Reads a 2D (VERTEX_SE2/EDGE_SE2, or TORO VERTEX2/EDGE2) or 3D (VERTEX_SE3:QUAT/EDGE_SE3:QUAT)
// pose graph, fixes the gauge by holding the first vertex (in file order) constant, and solves
// with Levenberg–Marquardt + SPARSE_NORMAL_CHOLESKY (SuiteSparse) unless told otherwise.
// Prints ONE JSON object on stdout (diagnostics go to stderr).
//
// WHAT IS TIMED: only the call to ceres::Solve() (wall clock, std::chrono::steady_clock).
// That includes Ceres' own preprocessing inside Solve (program reduction, Jacobian structure,
// symbolic analysis/ordering) plus all LM iterations. NOT timed: file parsing, building the
// ceres::Problem (cost functions, manifolds), and resetting the parameter blocks to the file's
// initial guess, which is done before every repeat.
//
// Objective (no ½; this is g2o's chi2 = 2 × Ceres' cost):
//   2D: e = [R(θz)ᵀ(R(θi)ᵀ(tj − ti) − tz); wrap(θj − θi − θz)] = t2v(Z⁻¹ Xi⁻¹ Xj),
//       residual r = Lᵀe with Ω = L Lᵀ, so ‖r‖² = eᵀΩe. Angles live on a wrapping manifold.
//   3D: Z⁻¹ Xi⁻¹ Xj is computed exactly as g2o's EdgeSE3 does (translation expressed in the
//       measurement frame), the rotation part is 2·vec(q_err) as in Ceres' pose_graph_3d example,
//       and the information applied to it is Ω' = D Ω D, D = diag(1,1,1,½,½,½). Then
//       ‖r‖² = [t; vec q]ᵀ Ω [t; vec q], i.e. Ceres minimises exactly g2o's objective.
//       (‖vec q‖ does not depend on the sign of q, so no w ≥ 0 normalisation is needed inside
//       the residual.) `final_chi2_g2o` is recomputed independently in double precision with the
//       file's Ω and w ≥ 0, as a cross-check.
//       Note: Ceres' own pose_graph_3d example uses a different error frame
//       (p_ab_est − p_ab_meas and q_meas·q_estᵀ); with the anisotropic rotation information of
//       e.g. sphere2500 that is a (slightly) different objective, hence the g2o form here.
//
// Output: {"system":"ceres","method":"lm","file","dim","poses","edges","initial_chi2","final_chi2",
//   ["initial_chi2_g2o","final_chi2_g2o" (3D only)],"iterations" (successful + unsuccessful steps),
//   "solve_seconds_runs","solve_seconds" (median),"converged" (termination == CONVERGENCE),
//   "termination","message", solver settings, "non_pd_information","blas","error"}.
//   On failure: {"system","method","file","error":"..."} and exit code 1.
//
// BLAS threads: OPENBLAS_NUM_THREADS etc. are set to --threads (unless already set) — see
// PinBlasThreads.
//
// Usage:
//   ceres_pose_graph --file PATH [--format auto|g2o|toro] [--repeat N] [--max-iterations 100]
//                    [--linear sparse_normal_cholesky|sparse_schur] [--threads 1] [--verbose]
//                    [--function-tolerance 1e-6] [--gradient-tolerance 1e-10] [--parameter-tolerance 1e-8]
//   --format auto (default): EDGE_SE2 lines use g2o information order, EDGE2 lines TORO order
//   (xx xy yy tt xt yt). --format g2o / toro forces that order for both tags.

#include <algorithm>
#include <chrono>
#include <cmath>
#include <climits>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include <unistd.h>

#include <Eigen/Core>
#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <ceres/autodiff_manifold.h>
#include <ceres/ceres.h>

namespace {

// ----------------------------------------------------------------------------------------------
// Data

struct Vertex2 { int id; double x, y, th; };
struct Edge2 { int i, j; double dx, dy, dth; Eigen::Matrix3d info; };
struct Vertex3 { int id; Eigen::Vector3d t; Eigen::Quaterniond q; };
struct Edge3 { int i, j; Eigen::Vector3d t; Eigen::Quaterniond q; Eigen::Matrix<double, 6, 6> info; };

struct Graph {
  int dim = 0;  // 2 or 3
  std::vector<Vertex2> v2;
  std::vector<Edge2> e2;
  std::vector<Vertex3> v3;
  std::vector<Edge3> e3;
};

struct Args {
  std::string file;
  std::string format = "auto";
  int repeat = 1;
  int max_iterations = 100;
  std::string linear = "sparse_normal_cholesky";
  int threads = 1;
  double function_tolerance = 1e-6;
  double gradient_tolerance = 1e-10;
  double parameter_tolerance = 1e-8;
  bool verbose = false;  // print Ceres' FullReport of the last run to stderr
};

// ----------------------------------------------------------------------------------------------
// Parsing

void SetDim(Graph& g, int d, int line_no) {
  if (g.dim != 0 && g.dim != d) {
    throw std::runtime_error("mixed 2D and 3D records (line " + std::to_string(line_no) + ")");
  }
  g.dim = d;
}

Graph ReadGraph(const std::string& path, const std::string& format) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open " + path);
  Graph g;
  std::string line, tag;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    std::istringstream ss(line);
    if (!(ss >> tag)) continue;
    auto bad = [&]() {
      return std::runtime_error("parse error at line " + std::to_string(line_no) + ": " + line);
    };
    if (tag == "VERTEX_SE2" || tag == "VERTEX2") {
      Vertex2 v;
      if (!(ss >> v.id >> v.x >> v.y >> v.th)) throw bad();
      SetDim(g, 2, line_no);
      g.v2.push_back(v);
    } else if (tag == "EDGE_SE2" || tag == "EDGE2") {
      Edge2 e;
      double f[6];
      if (!(ss >> e.i >> e.j >> e.dx >> e.dy >> e.dth)) throw bad();
      for (double& x : f) if (!(ss >> x)) throw bad();
      bool toro = (format == "toro") || (format == "auto" && tag == "EDGE2");
      if (toro) {  // xx xy yy tt xt yt
        e.info << f[0], f[1], f[4],
                  f[1], f[2], f[5],
                  f[4], f[5], f[3];
      } else {     // I11 I12 I13 I22 I23 I33
        e.info << f[0], f[1], f[2],
                  f[1], f[3], f[4],
                  f[2], f[4], f[5];
      }
      SetDim(g, 2, line_no);
      g.e2.push_back(e);
    } else if (tag == "VERTEX_SE3:QUAT") {
      Vertex3 v;
      double qx, qy, qz, qw;
      if (!(ss >> v.id >> v.t.x() >> v.t.y() >> v.t.z() >> qx >> qy >> qz >> qw)) throw bad();
      v.q = Eigen::Quaterniond(qw, qx, qy, qz).normalized();
      SetDim(g, 3, line_no);
      g.v3.push_back(v);
    } else if (tag == "EDGE_SE3:QUAT") {
      Edge3 e;
      double qx, qy, qz, qw;
      if (!(ss >> e.i >> e.j >> e.t.x() >> e.t.y() >> e.t.z() >> qx >> qy >> qz >> qw)) throw bad();
      e.q = Eigen::Quaterniond(qw, qx, qy, qz).normalized();
      for (int r = 0; r < 6; ++r) {
        for (int c = r; c < 6; ++c) {
          if (!(ss >> e.info(r, c))) throw bad();
          e.info(c, r) = e.info(r, c);
        }
      }
      SetDim(g, 3, line_no);
      g.e3.push_back(e);
    }
    // Anything else (FIX, EQUIV, comments, landmarks...) is ignored.
  }
  if (g.dim == 0) throw std::runtime_error("no pose-graph records found in " + path);
  if ((g.dim == 2 && g.v2.empty()) || (g.dim == 3 && g.v3.empty())) {
    throw std::runtime_error("file has no VERTEX records (edges-only graphs are not supported)");
  }
  return g;
}

// Number of information matrices that were not positive definite (reported in the JSON; such
// files were probably read with the wrong --format).
int g_non_pd_information = 0;

// Upper-triangular square root S of a symmetric PSD matrix A, with SᵀS = A (S = Lᵀ, A = L Lᵀ).
// Falls back to an eigen-decomposition square root if A is not numerically positive definite.
template <int N>
Eigen::Matrix<double, N, N> SqrtInformation(const Eigen::Matrix<double, N, N>& A) {
  Eigen::LLT<Eigen::Matrix<double, N, N>> llt(A);
  if (llt.info() == Eigen::Success) return llt.matrixU();
  ++g_non_pd_information;
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, N, N>> es(A);
  Eigen::Matrix<double, N, 1> ev = es.eigenvalues().cwiseMax(0.0).cwiseSqrt();
  return ev.asDiagonal() * es.eigenvectors().transpose();
}

// ----------------------------------------------------------------------------------------------
// 2D

// Wrap to (−π, π].
template <typename T>
T WrapAngle(const T& a) {
  const T two_pi(2.0 * M_PI);
  return a - two_pi * ceres::ceil((a - T(M_PI)) / two_pi);
}

struct AngleManifoldFunctor {
  template <typename T>
  bool Plus(const T* x, const T* delta, T* x_plus_delta) const {
    x_plus_delta[0] = WrapAngle(x[0] + delta[0]);
    return true;
  }
  template <typename T>
  bool Minus(const T* y, const T* x, T* y_minus_x) const {
    y_minus_x[0] = WrapAngle(y[0] - x[0]);
    return true;
  }
};

struct PoseGraph2dError {
  PoseGraph2dError(const Edge2& e) : dx(e.dx), dy(e.dy), dth(e.dth), sqrt_info(SqrtInformation<3>(e.info)) {}

  // Parameter blocks: position_i[2], theta_i[1], position_j[2], theta_j[1].
  template <typename T>
  bool operator()(const T* pi, const T* thi, const T* pj, const T* thj, T* residual) const {
    const T ci = ceres::cos(thi[0]), si = ceres::sin(thi[0]);
    const T ddx = pj[0] - pi[0], ddy = pj[1] - pi[1];
    // R(θi)ᵀ(tj − ti) − tz
    const T ux = ci * ddx + si * ddy - T(dx);
    const T uy = -si * ddx + ci * ddy - T(dy);
    // rotate into the measurement frame: R(θz)ᵀ u
    const double cz = std::cos(dth), sz = std::sin(dth);
    Eigen::Matrix<T, 3, 1> e;
    e(0) = T(cz) * ux + T(sz) * uy;
    e(1) = T(-sz) * ux + T(cz) * uy;
    e(2) = WrapAngle(thj[0] - thi[0] - T(dth));
    Eigen::Map<Eigen::Matrix<T, 3, 1>> r(residual);
    r = sqrt_info.template cast<T>() * e;
    return true;
  }

  double dx, dy, dth;
  Eigen::Matrix3d sqrt_info;
};

// ----------------------------------------------------------------------------------------------
// 3D

struct PoseGraph3dError {
  PoseGraph3dError(const Edge3& e) : t_z(e.t), q_z(e.q) {
    Eigen::Matrix<double, 6, 1> d;
    d << 1, 1, 1, 0.5, 0.5, 0.5;
    const Eigen::Matrix<double, 6, 6> info_ceres = d.asDiagonal() * e.info * d.asDiagonal();
    sqrt_info = SqrtInformation<6>(info_ceres);
  }

  // Parameter blocks: position_i[3], quaternion_i[4] (Eigen x,y,z,w), position_j[3], quaternion_j[4].
  template <typename T>
  bool operator()(const T* p_i_ptr, const T* q_i_ptr, const T* p_j_ptr, const T* q_j_ptr,
                  T* residual) const {
    Eigen::Map<const Eigen::Matrix<T, 3, 1>> p_i(p_i_ptr), p_j(p_j_ptr);
    Eigen::Map<const Eigen::Quaternion<T>> q_i(q_i_ptr), q_j(q_j_ptr);
    // X_i⁻¹ X_j
    const Eigen::Quaternion<T> q_i_inv = q_i.conjugate();
    const Eigen::Quaternion<T> q_ij = q_i_inv * q_j;
    const Eigen::Matrix<T, 3, 1> t_ij = q_i_inv * (p_j - p_i);
    // Z⁻¹ X_i⁻¹ X_j  (as g2o's EdgeSE3)
    const Eigen::Quaternion<T> q_z_inv = q_z.conjugate().template cast<T>();
    const Eigen::Quaternion<T> q_err = q_z_inv * q_ij;
    const Eigen::Matrix<T, 3, 1> t_err = q_z_inv * (t_ij - t_z.template cast<T>());
    Eigen::Matrix<T, 6, 1> e;
    e.template head<3>() = t_err;
    e.template tail<3>() = T(2.0) * q_err.vec();
    Eigen::Map<Eigen::Matrix<T, 6, 1>> r(residual);
    r = sqrt_info.template cast<T>() * e;
    return true;
  }

  Eigen::Vector3d t_z;
  Eigen::Quaterniond q_z;
  Eigen::Matrix<double, 6, 6> sqrt_info;
};

// g2o's chi2 for one 3D edge: e = [t_err; vec(q_err)] with q_err.w ≥ 0, eᵀΩe with the file's Ω.
double G2oChi2Edge3(const Edge3& e, const double* p_i, const double* q_i, const double* p_j,
                    const double* q_j) {
  Eigen::Map<const Eigen::Vector3d> pi(p_i), pj(p_j);
  Eigen::Map<const Eigen::Quaterniond> qi(q_i), qj(q_j);
  const Eigen::Quaterniond qi_inv = qi.conjugate();
  Eigen::Quaterniond q_err = e.q.conjugate() * (qi_inv * qj);
  q_err.normalize();
  if (q_err.w() < 0) q_err.coeffs() *= -1.0;
  const Eigen::Vector3d t_err = e.q.conjugate() * (qi_inv * (pj - pi) - e.t);
  Eigen::Matrix<double, 6, 1> err;
  err << t_err, q_err.vec();
  return err.dot(e.info * err);
}

// ----------------------------------------------------------------------------------------------
// Problem construction. Parameters live in `state`, laid out per vertex index; `initial` keeps the
// file's values so that every repeat starts from the same point.

struct Built {
  ceres::Problem problem;
  std::vector<double> state;    // 2D: [x y θ] per vertex; 3D: [x y z qx qy qz qw] per vertex
  std::vector<double> initial;
  int stride = 0;
  int fixed_vertex_id = -1;
  std::vector<std::pair<int, int>> edge_index;  // 3D: vertex indices per edge (for g2o chi2)
};

int IndexOf(const std::map<int, int>& idx, int id) {
  auto it = idx.find(id);
  if (it == idx.end()) throw std::runtime_error("edge refers to unknown vertex " + std::to_string(id));
  return it->second;
}

void Build(const Graph& g, Built& b) {
  std::map<int, int> idx;
  if (g.dim == 2) {
    b.stride = 3;
    b.initial.resize(3 * g.v2.size());
    for (size_t k = 0; k < g.v2.size(); ++k) {
      if (!idx.emplace(g.v2[k].id, static_cast<int>(k)).second)
        throw std::runtime_error("duplicate vertex id " + std::to_string(g.v2[k].id));
      b.initial[3 * k + 0] = g.v2[k].x;
      b.initial[3 * k + 1] = g.v2[k].y;
      b.initial[3 * k + 2] = WrapAngle(g.v2[k].th);
    }
    b.state = b.initial;
    auto* angle_manifold = new ceres::AutoDiffManifold<AngleManifoldFunctor, 1, 1>;
    for (const Edge2& e : g.e2) {
      const int i = IndexOf(idx, e.i), j = IndexOf(idx, e.j);
      double* xi = &b.state[3 * i];
      double* xj = &b.state[3 * j];
      auto* cost = new ceres::AutoDiffCostFunction<PoseGraph2dError, 3, 2, 1, 2, 1>(new PoseGraph2dError(e));
      b.problem.AddResidualBlock(cost, nullptr, xi, xi + 2, xj, xj + 2);
      b.problem.SetManifold(xi + 2, angle_manifold);
      b.problem.SetManifold(xj + 2, angle_manifold);
    }
    b.fixed_vertex_id = g.v2.front().id;
    double* x0 = &b.state[0];
    if (b.problem.HasParameterBlock(x0)) {
      b.problem.SetParameterBlockConstant(x0);
      b.problem.SetParameterBlockConstant(x0 + 2);
    }
  } else {
    b.stride = 7;
    b.initial.resize(7 * g.v3.size());
    for (size_t k = 0; k < g.v3.size(); ++k) {
      if (!idx.emplace(g.v3[k].id, static_cast<int>(k)).second)
        throw std::runtime_error("duplicate vertex id " + std::to_string(g.v3[k].id));
      double* s = &b.initial[7 * k];
      Eigen::Map<Eigen::Vector3d> t(s);
      Eigen::Map<Eigen::Quaterniond> q(s + 3);  // stored x, y, z, w
      t = g.v3[k].t;
      q = g.v3[k].q;
    }
    b.state = b.initial;
    auto* quat_manifold = new ceres::EigenQuaternionManifold;
    for (const Edge3& e : g.e3) {
      const int i = IndexOf(idx, e.i), j = IndexOf(idx, e.j);
      double* xi = &b.state[7 * i];
      double* xj = &b.state[7 * j];
      auto* cost = new ceres::AutoDiffCostFunction<PoseGraph3dError, 6, 3, 4, 3, 4>(new PoseGraph3dError(e));
      b.problem.AddResidualBlock(cost, nullptr, xi, xi + 3, xj, xj + 3);
      b.problem.SetManifold(xi + 3, quat_manifold);
      b.problem.SetManifold(xj + 3, quat_manifold);
      b.edge_index.emplace_back(i, j);
    }
    b.fixed_vertex_id = g.v3.front().id;
    double* x0 = &b.state[0];
    if (b.problem.HasParameterBlock(x0)) {
      b.problem.SetParameterBlockConstant(x0);
      b.problem.SetParameterBlockConstant(x0 + 3);
    }
  }
}

double G2oChi2(const Graph& g, const Built& b, const std::vector<double>& s) {
  double chi2 = 0.0;
  for (size_t k = 0; k < g.e3.size(); ++k) {
    const double* xi = &s[7 * b.edge_index[k].first];
    const double* xj = &s[7 * b.edge_index[k].second];
    chi2 += G2oChi2Edge3(g.e3[k], xi, xi + 3, xj, xj + 3);
  }
  return chi2;
}

// ----------------------------------------------------------------------------------------------
// Output helpers

std::string JsonString(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    switch (c) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\t': out += "\\t"; break;
      default:
        if (static_cast<unsigned char>(c) < 0x20) {
          char buf[8];
          std::snprintf(buf, sizeof buf, "\\u%04x", c);
          out += buf;
        } else {
          out += c;
        }
    }
  }
  return out + "\"";
}

std::string JsonNumber(double x) {
  if (!std::isfinite(x)) return "null";
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.17g", x);
  return buf;
}

double Median(std::vector<double> v) {
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

[[noreturn]] void Usage(const char* msg) {
  std::fprintf(stderr,
               "error: %s\nusage: ceres_pose_graph --file PATH [--format auto|g2o|toro] [--repeat N]\n"
               "       [--max-iterations 100] [--linear sparse_normal_cholesky|sparse_schur] [--threads 1]\n"
               "       [--verbose]   (Ceres FullReport of the last run on stderr)\n"
               "       [--function-tolerance 1e-6] [--gradient-tolerance 1e-10] [--parameter-tolerance 1e-8]\n",
               msg);
  std::exit(2);
}

Args ParseArgs(int argc, char** argv) {
  Args a;
  for (int k = 1; k < argc; ++k) {
    const std::string key = argv[k];
    if (key == "-h" || key == "--help") Usage("help requested");
    if (key == "--verbose") { a.verbose = true; continue; }
    if (k + 1 >= argc) Usage(("missing value for " + key).c_str());
    const std::string val = argv[++k];
    if (key == "--file") a.file = val;
    else if (key == "--format") a.format = val;
    else if (key == "--repeat") a.repeat = std::atoi(val.c_str());
    else if (key == "--max-iterations") a.max_iterations = std::atoi(val.c_str());
    else if (key == "--linear") a.linear = val;
    else if (key == "--threads") a.threads = std::atoi(val.c_str());
    else if (key == "--function-tolerance") a.function_tolerance = std::atof(val.c_str());
    else if (key == "--gradient-tolerance") a.gradient_tolerance = std::atof(val.c_str());
    else if (key == "--parameter-tolerance") a.parameter_tolerance = std::atof(val.c_str());
    else Usage(("unknown option " + key).c_str());
  }
  if (a.file.empty()) Usage("--file is required");
  if (a.format != "auto" && a.format != "g2o" && a.format != "toro") Usage("--format must be auto, g2o or toro");
  if (a.linear != "sparse_normal_cholesky" && a.linear != "sparse_schur") Usage("bad --linear");
  if (a.repeat < 1 || a.max_iterations < 1 || a.threads < 1) Usage("--repeat, --max-iterations, --threads must be >= 1");
  return a;
}

// CHOLMOD's supernodal factorisation calls BLAS. Keep BLAS at --threads so that a multithreaded
// OpenBLAS/MKL does not silently use extra cores. These variables are read when the BLAS library is
// loaded (before main for a dynamically linked BLAS), so set them and re-exec ourselves once.
void PinBlasThreads(int threads, char** argv) {
  if (std::getenv("CERES_POSE_GRAPH_REEXEC")) return;
  const std::string n = std::to_string(threads);
  bool changed = false;
  for (const char* var : {"OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "GOTO_NUM_THREADS"}) {
    if (!std::getenv(var)) {
      setenv(var, n.c_str(), 1);
      changed = true;
    }
  }
  if (changed) {
    setenv("CERES_POSE_GRAPH_REEXEC", "1", 1);
    execv("/proc/self/exe", argv);  // on failure we simply continue
  }
}

// Path of the BLAS library actually mapped into this process (Debian's libblas.so.3 is an
// alternatives symlink to ATLAS, OpenBLAS, reference BLAS, ...). Best effort.
std::string DetectBlas() {
  std::ifstream maps("/proc/self/maps");
  std::string line, found = "unknown";
  while (std::getline(maps, line)) {
    const size_t slash = line.find('/');
    if (slash == std::string::npos) continue;
    const std::string path = line.substr(slash);
    const std::string name = path.substr(path.rfind('/') + 1);
    const bool specific = name.find("openblas") != std::string::npos || name.find("atlas") != std::string::npos ||
                          name.find("mkl_rt") != std::string::npos || name.find("blis") != std::string::npos;
    if (specific || name.rfind("libblas.so", 0) == 0) {
      char real[4096];
      found = realpath(path.c_str(), real) ? real : path;
      if (specific) break;
    }
  }
  return found;
}

}  // namespace

int main(int argc, char** argv) {
  const Args args = ParseArgs(argc, argv);
  PinBlasThreads(args.threads, argv);
  std::ostringstream json;
  json << "{\"system\":\"ceres\",\"method\":\"lm\",\"file\":" << JsonString(args.file);
  try {
    const Graph g = ReadGraph(args.file, args.format);
    Built b;
    Build(g, b);

    ceres::Solver::Options opt;
    opt.minimizer_type = ceres::TRUST_REGION;
    opt.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
    opt.linear_solver_type =
        args.linear == "sparse_schur" ? ceres::SPARSE_SCHUR : ceres::SPARSE_NORMAL_CHOLESKY;
    opt.sparse_linear_algebra_library_type = ceres::SUITE_SPARSE;
    opt.num_threads = args.threads;
    opt.max_num_iterations = args.max_iterations;
    opt.function_tolerance = args.function_tolerance;
    opt.gradient_tolerance = args.gradient_tolerance;
    opt.parameter_tolerance = args.parameter_tolerance;
    opt.logging_type = ceres::SILENT;
    opt.minimizer_progress_to_stdout = false;
    std::string why;
    if (!opt.IsValid(&why)) throw std::runtime_error("invalid solver options: " + why);

    std::vector<double> runs;
    ceres::Solver::Summary summary;
    for (int r = 0; r < args.repeat; ++r) {
      std::copy(b.initial.begin(), b.initial.end(), b.state.begin());  // untimed reset
      summary = ceres::Solver::Summary();
      const auto t0 = std::chrono::steady_clock::now();
      ceres::Solve(opt, &b.problem, &summary);
      const auto t1 = std::chrono::steady_clock::now();
      runs.push_back(std::chrono::duration<double>(t1 - t0).count());
    }

    if (g_non_pd_information > 0) {
      std::fprintf(stderr, "warning: %d information matrices are not positive definite (wrong --format?); "
                   "used a clamped eigen-decomposition square root for them\n", g_non_pd_information);
    }
    if (args.verbose) std::fprintf(stderr, "%s\n", summary.FullReport().c_str());

    const size_t poses = g.dim == 2 ? g.v2.size() : g.v3.size();
    const size_t edges = g.dim == 2 ? g.e2.size() : g.e3.size();
    json << ",\"dim\":" << g.dim << ",\"poses\":" << poses << ",\"edges\":" << edges
         << ",\"initial_chi2\":" << JsonNumber(2.0 * summary.initial_cost)
         << ",\"final_chi2\":" << JsonNumber(2.0 * summary.final_cost);
    if (g.dim == 3) {
      json << ",\"initial_chi2_g2o\":" << JsonNumber(G2oChi2(g, b, b.initial))
           << ",\"final_chi2_g2o\":" << JsonNumber(G2oChi2(g, b, b.state));
    }
    json << ",\"iterations\":" << summary.num_successful_steps + summary.num_unsuccessful_steps
         << ",\"solve_seconds_runs\":[";
    for (size_t k = 0; k < runs.size(); ++k) json << (k ? "," : "") << JsonNumber(runs[k]);
    json << "],\"solve_seconds\":" << JsonNumber(Median(runs))
         << ",\"converged\":" << (summary.termination_type == ceres::CONVERGENCE ? "true" : "false")
         << ",\"termination\":" << JsonString(ceres::TerminationTypeToString(summary.termination_type))
         << ",\"message\":" << JsonString(summary.message)
         << ",\"linear_solver\":" << JsonString(args.linear)
         << ",\"threads\":" << args.threads
         << ",\"max_iterations\":" << args.max_iterations
         << ",\"function_tolerance\":" << JsonNumber(args.function_tolerance)
         << ",\"fixed_vertex\":" << b.fixed_vertex_id
         << ",\"non_pd_information\":" << g_non_pd_information
         << ",\"ceres_version\":" << JsonString(CERES_VERSION_STRING)
         << ",\"blas\":" << JsonString(DetectBlas())
         << ",\"error\":null}";
    std::printf("%s\n", json.str().c_str());
    return 0;
  } catch (const std::exception& ex) {
    json << ",\"error\":" << JsonString(ex.what()) << "}";
    std::printf("%s\n", json.str().c_str());
    return 1;
  }
}

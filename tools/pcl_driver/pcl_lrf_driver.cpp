// PCL 1.13 reference LRFs for lrf_jax: SHOT, BOARD, FLARE and RoPS frames of given keypoints.
//
// Usage:
//   pcl_lrf_driver --cloud bunny.ply --keypoints kp.txt --radius R --out DIR
//                  [--z-radius RZ] [--normals normals.txt] [--normal-radius RN]
//                  [--faces faces.txt] [--methods shot,board,flare,rops] [--repeat N]
//
//   --cloud       PLY (binary or ASCII; its faces are used by RoPS) or .xyz/.txt text "x y z" rows.
//   --keypoints   text file, one 0-based point index per line.
//   --radius      support radius r (cloud units): SHOT's search radius, BOARD/FLARE's tangent
//                 radius, RoPS's support radius.
//   --z-radius    BOARD/FLARE search radius for the z-axis (default r / 3, as lrf_jax).
//   --normals     text file "nx ny nz" per point, fed to BOARD and FLARE (so that lrf_jax can be
//                 fed the very same normals). Without it, PCL's NormalEstimation normals (radius
//                 --normal-radius, viewpoint at the origin) are used.
//   --normal-radius  radius of pcl::NormalEstimation (default r / 5); its normals at the keypoints
//                 are always written to DIR/pcl_normals.txt.
//   --faces       text file "i j k" per triangle, for a .xyz cloud.
//   --repeat      run each method N times and report the fastest (timing only).
//   --threads     OpenMP threads of the *_omp variants (default 2): "shot_omp" (PCL's
//                 SHOTLocalReferenceFrameEstimationOMP) and the "normals_omp" timing
//                 (NormalEstimationOMP over every point, the normals BOARD and FLARE need).
//
// Output (DIR): <method>.txt with one row per keypoint, 9 floats: x axis, y axis, z axis (rows
// of the LRF, NaN where PCL fails); pcl_normals.txt; timings.txt with "name seconds" lines.
// Timings include building the method's kd-tree and every radius search.
//
// RoPS: pcl::ROPSEstimation computes its LRF in the private member computeLRF(), called only
// from computeFeature() together with the (expensive) descriptor. We reach computeLRF() through
// the standard explicit-instantiation access idiom (access checks do not apply to explicit
// instantiations, [temp.explicit]/12 in C++17), and build its local surface exactly as its private
// getLocalSurface(): every triangle with at least one vertex within r of the keypoint.

#include <pcl/features/board.h>
#include <pcl/features/flare.h>
#include <pcl/features/normal_3d.h>
#include <pcl/features/rops_estimation.h>
#include <pcl/features/impl/rops_estimation.hpp>
#include <pcl/features/normal_3d_omp.h>
#include <pcl/features/shot_lrf.h>
#include <pcl/features/shot_lrf_omp.h>
#include <pcl/io/ply_io.h>
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl/point_types.h>
#include <pcl/search/kdtree.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

using PointT = pcl::PointXYZ;
using Cloud = pcl::PointCloud<PointT>;
using RopsT = pcl::ROPSEstimation<PointT, pcl::Histogram<135>>;

// ---- access to RoPS's private computeLRF (explicit-instantiation idiom) ----
template <typename Tag, typename Tag::type Member>
struct Expose {
  friend typename Tag::type get(Tag) { return Member; }
};
struct RopsComputeLRF {
  using type = void (RopsT::*)(const PointT&, const std::set<unsigned int>&,
                               Eigen::Matrix3f&) const;
  friend type get(RopsComputeLRF);
};
template struct Expose<RopsComputeLRF, &RopsT::computeLRF>;

namespace {

double now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

std::vector<std::vector<double>> read_rows(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open " + path);
  std::vector<std::vector<double>> rows;
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream ss(line);
    std::vector<double> row;
    double v;
    while (ss >> v) row.push_back(v);
    if (!row.empty()) rows.push_back(row);
  }
  return rows;
}

void write_frames(const std::string& path, const std::vector<Eigen::Matrix3f>& frames) {
  FILE* f = std::fopen(path.c_str(), "w");
  if (!f) throw std::runtime_error("cannot write " + path);
  for (const auto& m : frames) {
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) std::fprintf(f, "%.9g%c", m(r, c), (r == 2 && c == 2) ? '\n' : ' ');
  }
  std::fclose(f);
}

template <typename RF>
Eigen::Matrix3f to_matrix(const RF& rf) {
  Eigen::Matrix3f m;
  for (int d = 0; d < 3; ++d) {
    m(0, d) = rf.x_axis[d];
    m(1, d) = rf.y_axis[d];
    m(2, d) = rf.z_axis[d];
  }
  return m;
}

}  // namespace

int main(int argc, char** argv) {
  std::map<std::string, std::string> args;
  for (int i = 1; i + 1 < argc; i += 2) args[argv[i]] = argv[i + 1];
  for (const char* req : {"--cloud", "--keypoints", "--radius", "--out"}) {
    if (!args.count(req)) {
      std::cerr << "missing " << req << " (see the header of pcl_lrf_driver.cpp)\n";
      return 2;
    }
  }
  const float radius = std::stof(args["--radius"]);
  const float z_radius = args.count("--z-radius") ? std::stof(args["--z-radius"]) : radius / 3.0f;
  const float normal_radius =
      args.count("--normal-radius") ? std::stof(args["--normal-radius"]) : radius / 5.0f;
  const int repeat = args.count("--repeat") ? std::stoi(args["--repeat"]) : 1;
  const int threads = args.count("--threads") ? std::stoi(args["--threads"]) : 2;
  const std::string methods = args.count("--methods") ? args["--methods"] : "shot,board,flare,rops";
  const std::string out = args["--out"];

  // ---- cloud and faces ----
  Cloud::Ptr cloud(new Cloud);
  std::vector<pcl::Vertices> triangles;
  const std::string cloud_path = args["--cloud"];
  if (ends_with(cloud_path, ".ply")) {
    pcl::PolygonMesh mesh;
    if (pcl::io::loadPLYFile(cloud_path, mesh) < 0) {
      std::cerr << "cannot read " << cloud_path << "\n";
      return 1;
    }
    pcl::fromPCLPointCloud2(mesh.cloud, *cloud);
    triangles = mesh.polygons;
  } else {
    for (const auto& row : read_rows(cloud_path)) cloud->push_back(PointT(row[0], row[1], row[2]));
  }
  if (args.count("--faces")) {
    triangles.clear();
    for (const auto& row : read_rows(args["--faces"])) {
      pcl::Vertices v;
      v.vertices = {static_cast<pcl::index_t>(row[0]), static_cast<pcl::index_t>(row[1]),
                    static_cast<pcl::index_t>(row[2])};
      triangles.push_back(v);
    }
  }
  pcl::IndicesPtr keypoints(new pcl::Indices);
  for (const auto& row : read_rows(args["--keypoints"])) keypoints->push_back(static_cast<int>(row[0]));
  std::cerr << "cloud " << cloud->size() << " points, " << triangles.size() << " triangles, "
            << keypoints->size() << " keypoints, r = " << radius << "\n";

  std::ofstream timings(out + "/timings.txt");

  // ---- normals: PCL's NormalEstimation (always, for comparison) and the ones fed to BOARD/FLARE
  pcl::PointCloud<pcl::Normal>::Ptr pcl_normals(new pcl::PointCloud<pcl::Normal>);
  {
    double t0 = now();
    pcl::NormalEstimation<PointT, pcl::Normal> ne;
    ne.setInputCloud(cloud);
    ne.setSearchMethod(pcl::search::KdTree<PointT>::Ptr(new pcl::search::KdTree<PointT>));
    ne.setRadiusSearch(normal_radius);
    ne.compute(*pcl_normals);
    timings << "normals_all_points " << now() - t0 << "\n";
    FILE* f = std::fopen((out + "/pcl_normals.txt").c_str(), "w");
    for (int k : *keypoints) {
      const auto& n = (*pcl_normals)[k];
      std::fprintf(f, "%.9g %.9g %.9g\n", n.normal_x, n.normal_y, n.normal_z);
    }
    std::fclose(f);
  }
  pcl::PointCloud<pcl::Normal>::Ptr normals = pcl_normals;
  if (args.count("--normals")) {
    normals.reset(new pcl::PointCloud<pcl::Normal>);
    for (const auto& row : read_rows(args["--normals"])) normals->push_back(pcl::Normal(row[0], row[1], row[2]));
    if (normals->size() != cloud->size()) {
      std::cerr << "--normals: expected " << cloud->size() << " rows, got " << normals->size() << "\n";
      return 1;
    }
  }

  auto want = [&](const std::string& m) {
    return ("," + methods + ",").find("," + m + ",") != std::string::npos;
  };
  std::vector<Eigen::Matrix3f> frames(keypoints->size());

  // ---- multi-threaded variants: PCL's OMP normals (timing only) and SHOT LRF ----
  if (want("normals_omp")) {
    double best = std::numeric_limits<double>::max();
    for (int it = 0; it < repeat; ++it) {
      double t0 = now();
      pcl::NormalEstimationOMP<PointT, pcl::Normal> ne(threads);
      ne.setInputCloud(cloud);
      ne.setSearchMethod(pcl::search::KdTree<PointT>::Ptr(new pcl::search::KdTree<PointT>));
      ne.setRadiusSearch(normal_radius);
      pcl::PointCloud<pcl::Normal> tmp;
      ne.compute(tmp);
      best = std::min(best, now() - t0);
    }
    timings << "normals_omp " << best << "\n";
  }
  if (want("shot_omp")) {
    double best = std::numeric_limits<double>::max();
    for (int it = 0; it < repeat; ++it) {
      double t0 = now();
      pcl::SHOTLocalReferenceFrameEstimationOMP<PointT, pcl::ReferenceFrame> est;
      est.setNumberOfThreads(threads);
      est.setInputCloud(cloud);
      est.setIndices(keypoints);
      est.setSearchMethod(pcl::search::KdTree<PointT>::Ptr(new pcl::search::KdTree<PointT>));
      est.setRadiusSearch(radius);
      pcl::PointCloud<pcl::ReferenceFrame> rf;
      est.compute(rf);
      best = std::min(best, now() - t0);
      for (std::size_t i = 0; i < rf.size(); ++i) frames[i] = to_matrix(rf[i]);
    }
    timings << "shot_omp " << best << "\n";
    write_frames(out + "/shot_omp.txt", frames);
  }

  // ---- SHOT ----
  if (want("shot")) {
    double best = std::numeric_limits<double>::max();
    for (int it = 0; it < repeat; ++it) {
      double t0 = now();
      pcl::SHOTLocalReferenceFrameEstimation<PointT, pcl::ReferenceFrame> est;
      est.setInputCloud(cloud);
      est.setIndices(keypoints);
      est.setSearchMethod(pcl::search::KdTree<PointT>::Ptr(new pcl::search::KdTree<PointT>));
      est.setRadiusSearch(radius);
      pcl::PointCloud<pcl::ReferenceFrame> rf;
      est.compute(rf);
      best = std::min(best, now() - t0);
      for (std::size_t i = 0; i < rf.size(); ++i) frames[i] = to_matrix(rf[i]);
    }
    timings << "shot " << best << "\n";
    write_frames(out + "/shot.txt", frames);
  }

  // ---- BOARD ----
  if (want("board")) {
    double best = std::numeric_limits<double>::max();
    for (int it = 0; it < repeat; ++it) {
      double t0 = now();
      pcl::BOARDLocalReferenceFrameEstimation<PointT, pcl::Normal, pcl::ReferenceFrame> est;
      est.setInputCloud(cloud);
      est.setInputNormals(normals);
      est.setIndices(keypoints);
      est.setSearchMethod(pcl::search::KdTree<PointT>::Ptr(new pcl::search::KdTree<PointT>));
      est.setRadiusSearch(z_radius);
      est.setTangentRadius(radius);
      est.setFindHoles(false);
      pcl::PointCloud<pcl::ReferenceFrame> rf;
      est.compute(rf);
      best = std::min(best, now() - t0);
      for (std::size_t i = 0; i < rf.size(); ++i) frames[i] = to_matrix(rf[i]);
    }
    timings << "board " << best << "\n";
    write_frames(out + "/board.txt", frames);
  }

  // ---- FLARE ----
  if (want("flare")) {
    double best = std::numeric_limits<double>::max();
    for (int it = 0; it < repeat; ++it) {
      double t0 = now();
      pcl::FLARELocalReferenceFrameEstimation<PointT, pcl::Normal, pcl::ReferenceFrame> est;
      est.setInputCloud(cloud);
      est.setInputNormals(normals);
      est.setIndices(keypoints);
      est.setSearchMethod(pcl::search::KdTree<PointT>::Ptr(new pcl::search::KdTree<PointT>));
      est.setRadiusSearch(z_radius);
      est.setTangentRadius(radius);
      pcl::PointCloud<pcl::ReferenceFrame> rf;
      est.compute(rf);
      best = std::min(best, now() - t0);
      for (std::size_t i = 0; i < rf.size(); ++i) frames[i] = to_matrix(rf[i]);
    }
    timings << "flare " << best << "\n";
    write_frames(out + "/flare.txt", frames);
  }

  // ---- RoPS (LRF only) ----
  if (want("rops")) {
    if (triangles.empty()) {
      std::cerr << "rops: no triangles (pass a PLY with faces or --faces)\n";
    } else {
      double best = std::numeric_limits<double>::max();
      for (int it = 0; it < repeat; ++it) {
        double t0 = now();
        RopsT est;
        est.setInputCloud(cloud);
        est.setSearchSurface(cloud);
        est.setSupportRadius(radius);
        est.setTriangles(triangles);
        // As ROPSEstimation::buildListOfPointsTriangles and ::getLocalSurface.
        std::vector<std::vector<unsigned int>> triangles_of_point(cloud->size());
        for (std::size_t t = 0; t < triangles.size(); ++t)
          for (auto v : triangles[t].vertices) triangles_of_point[v].push_back(static_cast<unsigned int>(t));
        pcl::KdTreeFLANN<PointT> tree;
        tree.setInputCloud(cloud);
        const auto compute_lrf = get(RopsComputeLRF());
        for (std::size_t i = 0; i < keypoints->size(); ++i) {
          const PointT& p = (*cloud)[(*keypoints)[i]];
          pcl::Indices nb;
          std::vector<float> d2;
          tree.radiusSearch(p, radius, nb, d2);
          std::set<unsigned int> local_triangles;
          for (auto v : nb) local_triangles.insert(triangles_of_point[v].begin(), triangles_of_point[v].end());
          Eigen::Matrix3f lrf;
          (est.*compute_lrf)(p, local_triangles, lrf);
          frames[i] = lrf;
        }
        best = std::min(best, now() - t0);
      }
      timings << "rops " << best << "\n";
      write_frames(out + "/rops.txt", frames);
    }
  }
  return 0;
}

// PCL 1.13 reference descriptors for lrf_jax: SHOT352 and RoPS of given keypoints on GIVEN frames.
//
// Usage:
//   pcl_desc_driver --cloud cloud.txt --normals normals.txt --keypoints kp.txt --frames frames.txt
//                   --radius R --out DIR [--methods shot,rops] [--repeat N]
//
//   --cloud      text "x y z" per point (float32 values written exactly, %.9g).
//   --normals    text "nx ny nz" per point (NaN allowed), fed to SHOT (setInputNormals).
//   --keypoints  text, one 0-based point index per line.
//   --frames     text, one keypoint per line: 9 floats, the rows x, y, z of its LRF (world -> LRF).
//   --radius     support radius r (cloud units).
//   --repeat     run each method N times and report the fastest (timing only).
//
// Output (DIR): shot.txt (352 floats per keypoint, NaN where PCL fails), rops.txt (135 floats per
// keypoint) and timings.txt ("name seconds" lines; timings include building the kd-tree).
//
// SHOT: pcl::SHOTEstimation with setInputReferenceFrames (the public way to give external LRFs).
// RoPS: pcl::ROPSEstimation always computes its own (mesh) LRF inside the private computeFeature.
// To use an external LRF we repeat computeFeature's loop body here, line for line, but call PCL's
// own private transformCloud / rotateCloud / getDistributionMatrix / computeCentralMoments, reached
// through the explicit-instantiation access idiom (access checks do not apply to explicit
// instantiations, [temp.explicit]/12 in C++17). The local surface is getLocalSurface's point set:
// a kd-tree radius search of r around the keypoint (the triangles only feed the LRF).

#include <pcl/features/rops_estimation.h>
#include <pcl/features/impl/rops_estimation.hpp>
#include <pcl/features/shot.h>
#include <pcl/kdtree/kdtree_flann.h>
#include <pcl/point_types.h>
#include <pcl/search/kdtree.h>

#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <limits>
#include <map>
#include <numeric>
#include <sstream>
#include <string>
#include <vector>

using PointT = pcl::PointXYZ;
using Cloud = pcl::PointCloud<PointT>;
using RopsT = pcl::ROPSEstimation<PointT, pcl::Histogram<135>>;

// ---- access to RoPS's private members (explicit-instantiation idiom) ----
template <typename Tag, typename Tag::type Member>
struct Expose {
  friend typename Tag::type get(Tag) { return Member; }
};
struct TransformCloudTag {
  using type = void (RopsT::*)(const PointT&, const Eigen::Matrix3f&, const pcl::Indices&,
                               Cloud&) const;
  friend type get(TransformCloudTag);
};
struct RotateCloudTag {
  using type = void (RopsT::*)(const PointT&, const float, const Cloud&, Cloud&, Eigen::Vector3f&,
                               Eigen::Vector3f&) const;
  friend type get(RotateCloudTag);
};
struct DistributionTag {
  using type = void (RopsT::*)(const unsigned int, const Eigen::Vector3f&, const Eigen::Vector3f&,
                               const Cloud&, Eigen::MatrixXf&) const;
  friend type get(DistributionTag);
};
struct MomentsTag {
  using type = void (RopsT::*)(const Eigen::MatrixXf&, std::vector<float>&) const;
  friend type get(MomentsTag);
};
struct StepTag {
  using type = float RopsT::*;
  friend type get(StepTag);
};
struct BinsTag {
  using type = unsigned int RopsT::*;
  friend type get(BinsTag);
};
template struct Expose<TransformCloudTag, &RopsT::transformCloud>;
template struct Expose<RotateCloudTag, &RopsT::rotateCloud>;
template struct Expose<DistributionTag, &RopsT::getDistributionMatrix>;
template struct Expose<MomentsTag, &RopsT::computeCentralMoments>;
template struct Expose<StepTag, &RopsT::step_>;
template struct Expose<BinsTag, &RopsT::number_of_bins_>;

namespace {

double now() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

std::vector<std::vector<double>> read_rows(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open " + path);
  std::vector<std::vector<double>> rows;
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream ss(line);
    std::vector<double> row;
    std::string tok;
    while (ss >> tok) row.push_back(std::stod(tok));  // stod parses "nan"
    if (!row.empty()) rows.push_back(row);
  }
  return rows;
}

void write_rows(const std::string& path, const std::vector<std::vector<float>>& rows) {
  FILE* f = std::fopen(path.c_str(), "w");
  if (!f) throw std::runtime_error("cannot write " + path);
  for (const auto& row : rows)
    for (std::size_t i = 0; i < row.size(); ++i)
      std::fprintf(f, "%.9g%c", row[i], i + 1 == row.size() ? '\n' : ' ');
  std::fclose(f);
}

// RoPS of one keypoint on an external LRF: the body of ROPSEstimation::computeFeature with
// computeLRF replaced by `lrf`.
std::vector<float> rops_with_lrf(const RopsT& rops, const pcl::KdTreeFLANN<PointT>& tree,
                                 const Cloud& cloud, int keypoint, const Eigen::Matrix3f& lrf,
                                 float radius) {
  const PointT& point = cloud[keypoint];
  pcl::Indices local_points;
  std::vector<float> distances;
  tree.radiusSearch(point, radius, local_points, distances);

  Cloud transformed_cloud;
  (rops.*get(TransformCloudTag()))(point, lrf, local_points, transformed_cloud);

  std::array<PointT, 3> axes;
  axes[0].x = 1.0f; axes[0].y = 0.0f; axes[0].z = 0.0f;
  axes[1].x = 0.0f; axes[1].y = 1.0f; axes[1].z = 0.0f;
  axes[2].x = 0.0f; axes[2].y = 0.0f; axes[2].z = 1.0f;
  const float step = rops.*get(StepTag());
  const unsigned int bins = rops.*get(BinsTag());
  std::vector<float> feature;
  for (const auto& axis : axes) {
    float theta = step;
    do {
      Cloud rotated_cloud;
      Eigen::Vector3f min, max;
      (rops.*get(RotateCloudTag()))(axis, theta, transformed_cloud, rotated_cloud, min, max);
      for (unsigned int i_proj = 0; i_proj < 3; i_proj++) {
        Eigen::MatrixXf distribution_matrix;
        distribution_matrix.resize(bins, bins);
        (rops.*get(DistributionTag()))(i_proj, min, max, rotated_cloud, distribution_matrix);
        std::vector<float> moments;
        (rops.*get(MomentsTag()))(distribution_matrix, moments);
        feature.insert(feature.end(), moments.begin(), moments.end());
      }
      theta += step;
    } while (theta < 90.0f);
  }
  const float norm = std::accumulate(feature.cbegin(), feature.cend(), 0.f,
                                     [](const auto& sum, const auto& val) { return sum + std::abs(val); });
  const float invert_norm = norm < std::numeric_limits<float>::epsilon() ? 1.0f : 1.0f / norm;
  for (auto& v : feature) v *= invert_norm;
  return feature;
}

}  // namespace

int main(int argc, char** argv) {
  std::map<std::string, std::string> args;
  for (int i = 1; i + 1 < argc; i += 2) args[argv[i]] = argv[i + 1];
  for (const char* req : {"--cloud", "--normals", "--keypoints", "--frames", "--radius", "--out"}) {
    if (!args.count(req)) {
      std::cerr << "missing " << req << " (see the header of pcl_desc_driver.cpp)\n";
      return 2;
    }
  }
  const float radius = std::stof(args["--radius"]);
  const int repeat = args.count("--repeat") ? std::stoi(args["--repeat"]) : 1;
  const std::string methods = args.count("--methods") ? args["--methods"] : "shot,rops";
  const std::string out = args["--out"];

  Cloud::Ptr cloud(new Cloud);
  for (const auto& row : read_rows(args["--cloud"])) cloud->push_back(PointT(row[0], row[1], row[2]));
  pcl::PointCloud<pcl::Normal>::Ptr normals(new pcl::PointCloud<pcl::Normal>);
  for (const auto& row : read_rows(args["--normals"]))
    normals->push_back(pcl::Normal(row[0], row[1], row[2]));
  if (normals->size() != cloud->size()) {
    std::cerr << "--normals: expected " << cloud->size() << " rows, got " << normals->size() << "\n";
    return 1;
  }
  pcl::IndicesPtr keypoints(new pcl::Indices);
  for (const auto& row : read_rows(args["--keypoints"])) keypoints->push_back(static_cast<int>(row[0]));
  const auto frame_rows = read_rows(args["--frames"]);
  if (frame_rows.size() != keypoints->size()) {
    std::cerr << "--frames: expected " << keypoints->size() << " rows, got " << frame_rows.size() << "\n";
    return 1;
  }
  pcl::PointCloud<pcl::ReferenceFrame>::Ptr frames(new pcl::PointCloud<pcl::ReferenceFrame>);
  std::vector<Eigen::Matrix3f> lrfs;
  for (const auto& row : frame_rows) {
    pcl::ReferenceFrame rf;
    Eigen::Matrix3f m;
    for (int d = 0; d < 3; ++d) {
      rf.x_axis[d] = row[d];
      rf.y_axis[d] = row[3 + d];
      rf.z_axis[d] = row[6 + d];
      m(0, d) = row[d];
      m(1, d) = row[3 + d];
      m(2, d) = row[6 + d];
    }
    frames->push_back(rf);
    lrfs.push_back(m);
  }
  std::cerr << "cloud " << cloud->size() << " points, " << keypoints->size()
            << " keypoints, r = " << radius << "\n";
  std::ofstream timings(out + "/timings.txt");
  auto want = [&](const std::string& m) { return methods.find(m) != std::string::npos; };

  if (want("shot")) {
    pcl::PointCloud<pcl::SHOT352> result;
    double best = std::numeric_limits<double>::max();
    for (int it = 0; it < repeat; ++it) {
      double t0 = now();
      pcl::SHOTEstimation<PointT, pcl::Normal, pcl::SHOT352, pcl::ReferenceFrame> shot;
      shot.setInputCloud(cloud);
      shot.setIndices(keypoints);
      shot.setInputNormals(normals);
      shot.setInputReferenceFrames(frames);
      shot.setSearchMethod(pcl::search::KdTree<PointT>::Ptr(new pcl::search::KdTree<PointT>));
      shot.setRadiusSearch(radius);
      shot.compute(result);
      best = std::min(best, now() - t0);
    }
    timings << "shot " << best << "\n";
    std::vector<std::vector<float>> rows;
    for (const auto& d : result) rows.emplace_back(d.descriptor, d.descriptor + 352);
    write_rows(out + "/shot.txt", rows);
  }

  if (want("rops")) {
    std::vector<std::vector<float>> rows;
    double best = std::numeric_limits<double>::max();
    for (int it = 0; it < repeat; ++it) {
      double t0 = now();
      RopsT rops;  // defaults: 5 bins, 3 rotations (PCL's tutorial values)
      rops.setInputCloud(cloud);
      rops.setSearchSurface(cloud);
      rops.setSupportRadius(radius);
      pcl::KdTreeFLANN<PointT> tree;
      tree.setInputCloud(cloud);
      rows.clear();
      for (std::size_t i = 0; i < keypoints->size(); ++i)
        rows.push_back(rops_with_lrf(rops, tree, *cloud, (*keypoints)[i], lrfs[i], radius));
      best = std::min(best, now() - t0);
    }
    timings << "rops " << best << "\n";
    write_rows(out + "/rops.txt", rows);
  }
  return 0;
}

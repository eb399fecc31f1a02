// Peer for benchmarks/bench_triangulation.py: a plain C++ program that builds
// CGAL's dD Delaunay triangulation directly, the way CGAL's documentation does
// (Epick_d, insert(range) with its spatial sort). The benchmark compiles it
// with the same flags as flatserve._core and compares build times.
//
// usage: cgal_build_peer POINTS.bin [repeats]
//   POINTS.bin: int64 n, int64 D, then n*D float64 (row-major)
// prints one line per repeat: "seconds <t> vertices <n> cells <m>", then
// "peak_rss_kb <k>".
#include <CGAL/Delaunay_triangulation.h>
#include <CGAL/Epick_d.h>

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#ifndef PEER_DIM
#define PEER_DIM 4
#endif

using K = CGAL::Epick_d<CGAL::Dimension_tag<PEER_DIM>>;
using DT = CGAL::Delaunay_triangulation<K>;
using Point = K::Point_d;

int main(int argc, char** argv) {
  if (argc < 2) {
    std::cerr << "usage: " << argv[0] << " POINTS.bin [repeats]\n";
    return 2;
  }
  int repeats = argc > 2 ? std::atoi(argv[2]) : 1;
  std::ifstream in(argv[1], std::ios::binary);
  std::int64_t n = 0, D = 0;
  in.read(reinterpret_cast<char*>(&n), 8);
  in.read(reinterpret_cast<char*>(&D), 8);
  if (!in || D != PEER_DIM) {
    std::cerr << "bad file or dimension (compiled for " << PEER_DIM << ")\n";
    return 2;
  }
  std::vector<double> raw(static_cast<std::size_t>(n * D));
  in.read(reinterpret_cast<char*>(raw.data()), static_cast<std::streamsize>(raw.size() * 8));
  if (!in) {
    std::cerr << "truncated file\n";
    return 2;
  }
  for (int r = 0; r < repeats; ++r) {
    std::vector<Point> pts;
    pts.reserve(static_cast<std::size_t>(n));
    auto t0 = std::chrono::steady_clock::now();
    for (std::int64_t i = 0; i < n; ++i) pts.emplace_back(&raw[i * D], &raw[(i + 1) * D]);
    DT dt(PEER_DIM);
    dt.insert(pts.begin(), pts.end());
    auto t1 = std::chrono::steady_clock::now();
    std::printf("seconds %.6f vertices %zu cells %zu\n",
                std::chrono::duration<double>(t1 - t0).count(), dt.number_of_vertices(),
                dt.number_of_full_cells());
    std::fflush(stdout);
  }
  // VmHWM: this process image's peak RSS (ru_maxrss would include the
  // parent's peak, which Linux carries across fork + exec).
  long hwm = -1;
  std::ifstream status("/proc/self/status");
  for (std::string line; std::getline(status, line);)
    if (line.rfind("VmHWM:", 0) == 0) hwm = std::atol(line.c_str() + 6);
  std::printf("peak_rss_kb %ld\n", hwm);
  return 0;
}

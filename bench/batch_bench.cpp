// Batch conversion as a user runs it (a timed CLI run): 200 generated CL files of 10,000 points each (smooth
// variable-axis rasters over domes, different for every file) converted by `cscam post FILES -o DIR/` with
// CSCAM_THREADS=1 and =2. Prints files/s at each and the speed-up (target >= 1.8x on 2 cores), and checks that
// both runs wrote the same bytes. Usage: batch_bench [files] [points]
#include <fmt/format.h>
#include <sys/resource.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <random>
#include <sstream>
#include <string>

namespace fs = std::filesystem;

namespace {

void make_cl(const fs::path& path, unsigned seed, std::size_t points) {
  std::mt19937_64 g(20261122u + seed);
  std::uniform_real_distribution<double> u(-10.0, 10.0);
  const double cx = u(g), cy = u(g), R = 180.0 + 2.0 * u(g);
  std::ofstream out(path);
  out << "PARTNO BATCH " << seed << "\nUNITS/MM\nMULTAX/ON\nCUTTER/10,5\nLOADTL/1\nSPINDL/8000,CLW\nFEDRAT/MMPM,2000\n";
  const std::size_t per_row = 500;
  const std::size_t rows = (points + per_row - 1) / per_row;
  for (std::size_t i = 0; i < points; ++i) {
    const std::size_t row = i / per_row, k = i % per_row;
    const double x = cx - 70.0 + 140.0 * static_cast<double>(row % 2 ? per_row - 1 - k : k) / (per_row - 1);
    const double y =
        cy - 70.0 + 140.0 * static_cast<double>(row) / static_cast<double>(std::max<std::size_t>(rows - 1, 1));
    const double zz = std::sqrt(R * R - (x - cx) * (x - cx) - (y - cy) * (y - cy));
    if (k == 0) out << "RAPID\n";
    // The dome stands 60 mm above the platter face (the part origin): its edge at z >= 30 mm, where the tilted
    // holder clears the machine's table (machines/trunnion-ac.yaml's bodies; at +20 every file collided with it).
    out << fmt::format("GOTO/{:.4f},{:.4f},{:.4f},{:.7f},{:.7f},{:.7f}\n", x, y, zz - R + 60.0, (x - cx) / R,
                       (y - cy) / R, zz / R);
  }
  out << "FINI\n";
}

double load() {
  double l[1] = {0};
  return ::getloadavg(l, 1) == 1 ? l[0] : -1.0;
}

/// CPU seconds (user + system) used by finished child processes so far.
double children_cpu_s() {
  rusage ru{};
  ::getrusage(RUSAGE_CHILDREN, &ru);
  return static_cast<double>(ru.ru_utime.tv_sec + ru.ru_stime.tv_sec) +
         1e-6 * static_cast<double>(ru.ru_utime.tv_usec + ru.ru_stime.tv_usec);
}

std::string slurp(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), {});
}

}  // namespace

int main(int argc, char** argv) {
  const std::size_t files = argc > 1 ? std::stoul(argv[1]) : 200;
  const std::size_t points = argc > 2 ? std::stoul(argv[2]) : 10000;
  const fs::path dir = fs::temp_directory_path() / fmt::format("cscam_batch_bench_{}", ::getpid());
  fs::create_directories(dir / "cl");
  std::string list;
  for (std::size_t i = 0; i < files; ++i) {
    const fs::path p = dir / "cl" / fmt::format("part{:03d}.cls", i);
    make_cl(p, static_cast<unsigned>(i), points);
    list += " " + p.string();
  }
  double secs[3] = {0, 0, 0};
  for (int threads : {1, 2}) {
    const fs::path out = dir / fmt::format("out{}", threads);
    const std::string cmd = fmt::format("CSCAM_THREADS={} {} post{} --machine trunnion-ac -o {}/ > {}/log{}.txt 2>&1",
                                        threads, CSCAM_CLI, list, out.string(), dir.string(), threads);
    const auto t0 = std::chrono::steady_clock::now();
    const double cpu0 = children_cpu_s();
    const int rc = std::system(cmd.c_str());
    const double cpu = children_cpu_s() - cpu0;
    secs[threads] = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (rc != 0) {
      std::cerr << "batch failed (" << rc << "):\n" << slurp(dir / fmt::format("log{}.txt", threads));
      fs::remove_all(dir);
      return 1;
    }
    // CPU time too: on a shared machine the wall time depends on the others' load, the CPU time does not.
    std::cout << fmt::format(
        "{} files x {} points, {} thread(s): {:.2f} s wall, {:.2f} s CPU, {:.1f} files/s, {:.0f} CL points/s; "
        "load average {:.1f}\n",
        files, points, threads, secs[threads], cpu, files / secs[threads],
        static_cast<double>(files * points) / secs[threads], load());
  }
  std::size_t same = 0;
  for (std::size_t i = 0; i < files; ++i) {
    const std::string n = fmt::format("part{:03d}.ngc", i);
    same += slurp(dir / "out1" / n) == slurp(dir / "out2" / n);
  }
  std::cout << fmt::format("speed-up 2 threads over 1: {:.2f}x (target >= 1.8x); outputs identical: {}/{}\n",
                           secs[1] / secs[2], same, files);
  fs::remove_all(dir);
  return same == files ? 0 : 1;
}

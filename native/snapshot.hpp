// Binary snapshot format of a flatserve triangulation (no Python, no CGAL
// geometry: only the combinatorial structure and the numbers).
//
// Layout (little-endian, fixed 80-byte header, then the payload):
//
//   offset  type      field
//   0       char[8]   magic "FSTRIANG"
//   8       u32       version (1)
//   12      u32       header size in bytes (80)
//   16      i32       maximal dimension D
//   20      i32       current dimension cd (D, or less for a degenerate set)
//   24      u64       n   finite vertices
//   32      u64       m   full cells, infinite ones included (0 when cd < D)
//   40      u64       C   value channels (0: no values stored)
//   48      u64       payload size in bytes
//   56      u64       payload checksum (see Checksum)
//   64      u64       endianness marker 0x0102030405060708
//   72      u64       header checksum (of bytes 0..71)
//
//   payload:
//     points      n x D   f64   vertex coordinates, in sample-id order
//     ids         n       i64   sample id of each vertex (== row index)
//     cells       m x (D+1) u32 vertex indices: 0 = infinite vertex,
//                                i + 1 = the vertex in row i above
//     neighbours  m x (D+1) u32 full-cell index of the neighbour opposite
//                                each vertex of the cell
//     vertex cells (n+1)  u32   a full cell of each vertex (infinite first);
//                                walks start there (only when m > 0)
//     values      n x C   f64   sample values (row = sample id)
//
//   Cells are numbered in file order: the finite ones first (their index is
//   the row of Triangulation.simplices), then the infinite ones.
//
// Reading rebuilds CGAL's triangulation data structure directly (vertices,
// full cells, neighbours, current dimension), like CGAL's operator>> for
// Triangulation_data_structure, but without per-element stream extraction and
// without recomputing mirror indices (the default full-cell storage policy does
// not store them). A degenerate triangulation (cd < D) stores no cells and is
// rebuilt by insertion of its (few, coplanar) points.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <stdexcept>
#include <string>
#include <vector>

namespace flatserve {

// Any problem with a snapshot: truncated, corrupted, other version, I/O.
struct snapshot_error : std::runtime_error {
  using std::runtime_error::runtime_error;
};

constexpr char kSnapshotMagic[8] = {'F', 'S', 'T', 'R', 'I', 'A', 'N', 'G'};
constexpr std::uint32_t kSnapshotVersion = 1;
constexpr std::uint32_t kHeaderSize = 80;
constexpr std::uint64_t kEndianMarker = 0x0102030405060708ull;

struct SnapshotHeader {
  std::int32_t dim = 0;
  std::int32_t current_dim = -1;
  std::uint64_t n_vertices = 0;
  std::uint64_t n_cells = 0;
  std::uint64_t n_channels = 0;
  std::uint64_t payload_bytes = 0;
  std::uint64_t payload_checksum = 0;
};

// Streaming 64-bit checksum: four FNV-1a-style lanes over 8-byte little-endian
// words (xor then multiply by the FNV prime), folded with the length at the
// end. Any change confined to one word is always detected (both steps are
// bijections); it runs at memory speed, unlike byte-wise FNV or CRC32.
class Checksum {
 public:
  void update(const void* data, std::size_t len) {
    const unsigned char* p = static_cast<const unsigned char*>(data);
    total_ += len;
    if (fill_) {
      std::size_t take = std::min(len, sizeof(buf_) - fill_);
      std::memcpy(buf_ + fill_, p, take);
      fill_ += take;
      p += take;
      len -= take;
      if (fill_ == sizeof(buf_)) {
        block(buf_);
        fill_ = 0;
      }
    }
    while (len >= sizeof(buf_)) {
      block(p);
      p += sizeof(buf_);
      len -= sizeof(buf_);
    }
    if (len) {
      std::memcpy(buf_, p, len);
      fill_ = len;
    }
  }
  std::uint64_t digest() const {
    std::uint64_t l[4] = {lane_[0], lane_[1], lane_[2], lane_[3]};
    if (fill_) {
      unsigned char tail[32] = {0};
      std::memcpy(tail, buf_, fill_);
      for (int k = 0; k < 4; ++k) l[k] = mix(l[k], load(tail + 8 * k));
    }
    std::uint64_t h = kBasis;
    for (int k = 0; k < 4; ++k) h = mix(h, l[k]);
    h = mix(h, static_cast<std::uint64_t>(total_));
    return h ^ (h >> 29);
  }

 private:
  static constexpr std::uint64_t kBasis = 0xcbf29ce484222325ull;
  static constexpr std::uint64_t kPrime = 0x100000001b3ull;
  static std::uint64_t load(const unsigned char* p) {
    std::uint64_t w;
    std::memcpy(&w, p, 8);
    return w;
  }
  static std::uint64_t mix(std::uint64_t h, std::uint64_t w) { return (h ^ w) * kPrime; }
  void block(const unsigned char* p) {
    for (int k = 0; k < 4; ++k) lane_[k] = mix(lane_[k], load(p + 8 * k));
  }
  std::uint64_t lane_[4] = {kBasis, kBasis ^ 1, kBasis ^ 2, kBasis ^ 3};
  unsigned char buf_[32];
  std::size_t fill_ = 0;
  std::uint64_t total_ = 0;
};

// ---------------------------------------------------------------- sinks
class Sink {
 public:
  virtual ~Sink() = default;
  virtual void write(const void* data, std::size_t len) = 0;
  // Overwrite the first bytes (the header) once the payload is written.
  virtual void patch_front(const void* data, std::size_t len) = 0;
};

class VectorSink final : public Sink {
 public:
  std::vector<char> buf;
  void write(const void* data, std::size_t len) override {
    const char* p = static_cast<const char*>(data);
    buf.insert(buf.end(), p, p + len);
  }
  void patch_front(const void* data, std::size_t len) override {
    std::memcpy(buf.data(), data, len);
  }
};

class FileSink final : public Sink {
 public:
  explicit FileSink(const std::string& path) : path_(path) {
    f_ = std::fopen(path.c_str(), "wb");
    if (!f_) throw snapshot_error("cannot open '" + path + "' for writing");
    std::setvbuf(f_, nullptr, _IOFBF, 1 << 22);
  }
  ~FileSink() override {
    if (f_) std::fclose(f_);
  }
  void write(const void* data, std::size_t len) override {
    if (len && std::fwrite(data, 1, len, f_) != len)
      throw snapshot_error("write error on '" + path_ + "' (disk full?)");
  }
  void patch_front(const void* data, std::size_t len) override {
    if (std::fflush(f_) != 0 || std::fseek(f_, 0, SEEK_SET) != 0)
      throw snapshot_error("seek error on '" + path_ + "'");
    write(data, len);
  }
  void close() {
    int rc = std::fclose(f_);
    f_ = nullptr;
    if (rc != 0) throw snapshot_error("close error on '" + path_ + "' (disk full?)");
  }

 private:
  std::FILE* f_ = nullptr;
  std::string path_;
};

// Buffers writes, checksums the payload as it passes.
class PayloadWriter {
 public:
  explicit PayloadWriter(Sink& s) : sink_(s) { buf_.reserve(kBuf); }
  void write(const void* data, std::size_t len) {
    sum_.update(data, len);
    bytes_ += len;
    const char* p = static_cast<const char*>(data);
    if (buf_.size() + len > kBuf) flush();
    if (len >= kBuf) {
      sink_.write(p, len);
      return;
    }
    buf_.insert(buf_.end(), p, p + len);
  }
  template <class T>
  void put(const T& v) {
    write(&v, sizeof(T));
  }
  void flush() {
    if (!buf_.empty()) sink_.write(buf_.data(), buf_.size());
    buf_.clear();
  }
  std::uint64_t checksum() const { return sum_.digest(); }
  std::uint64_t bytes() const { return bytes_; }

 private:
  static constexpr std::size_t kBuf = 1 << 20;
  Sink& sink_;
  std::vector<char> buf_;
  Checksum sum_;
  std::uint64_t bytes_ = 0;
};

// ---------------------------------------------------------------- sources
class Source {
 public:
  virtual ~Source() = default;
  // Reads exactly len bytes or throws snapshot_error("truncated ...").
  virtual void read(void* data, std::size_t len, const char* what) = 0;
  // Bytes left after the current position (for an early truncation check).
  virtual std::uint64_t remaining() const = 0;
};

class MemorySource final : public Source {
 public:
  MemorySource(const char* data, std::size_t len) : p_(data), left_(len) {}
  void read(void* data, std::size_t len, const char* what) override {
    if (len > left_)
      throw snapshot_error(std::string("snapshot truncated while reading ") + what);
    std::memcpy(data, p_, len);
    p_ += len;
    left_ -= len;
  }
  std::uint64_t remaining() const override { return left_; }

 private:
  const char* p_;
  std::size_t left_;
};

class FileSource final : public Source {
 public:
  explicit FileSource(const std::string& path) : path_(path) {
    f_ = std::fopen(path.c_str(), "rb");
    if (!f_) throw snapshot_error("cannot open '" + path + "' for reading");
    std::setvbuf(f_, nullptr, _IOFBF, 1 << 22);
    if (std::fseek(f_, 0, SEEK_END) != 0) throw snapshot_error("cannot seek '" + path + "'");
    long end = std::ftell(f_);
    if (end < 0) throw snapshot_error("cannot size '" + path + "'");
    size_ = static_cast<std::uint64_t>(end);
    std::fseek(f_, 0, SEEK_SET);
  }
  ~FileSource() override {
    if (f_) std::fclose(f_);
  }
  void read(void* data, std::size_t len, const char* what) override {
    if (len && std::fread(data, 1, len, f_) != len)
      throw snapshot_error(std::string("snapshot '") + path_ + "' truncated while reading " + what);
    pos_ += len;
  }
  std::uint64_t remaining() const override { return size_ > pos_ ? size_ - pos_ : 0; }

 private:
  std::FILE* f_ = nullptr;
  std::string path_;
  std::uint64_t size_ = 0, pos_ = 0;
};

// Reads the payload in chunks, checksumming as it goes.
class PayloadReader {
 public:
  explicit PayloadReader(Source& s) : src_(s) {}
  void read(void* data, std::size_t len, const char* what) {
    src_.read(data, len, what);
    sum_.update(data, len);
  }
  std::uint64_t checksum() const { return sum_.digest(); }

 private:
  Source& src_;
  Checksum sum_;
};

// ---------------------------------------------------------------- header
inline void encode_header(const SnapshotHeader& h, unsigned char out[kHeaderSize]) {
  std::memset(out, 0, kHeaderSize);
  std::memcpy(out, kSnapshotMagic, 8);
  std::memcpy(out + 8, &kSnapshotVersion, 4);
  std::memcpy(out + 12, &kHeaderSize, 4);
  std::memcpy(out + 16, &h.dim, 4);
  std::memcpy(out + 20, &h.current_dim, 4);
  std::memcpy(out + 24, &h.n_vertices, 8);
  std::memcpy(out + 32, &h.n_cells, 8);
  std::memcpy(out + 40, &h.n_channels, 8);
  std::memcpy(out + 48, &h.payload_bytes, 8);
  std::memcpy(out + 56, &h.payload_checksum, 8);
  std::memcpy(out + 64, &kEndianMarker, 8);
  Checksum c;
  c.update(out, 72);
  std::uint64_t hc = c.digest();
  std::memcpy(out + 72, &hc, 8);
}

// Multiplication / addition that report overflow (sizes come from a file).
inline bool mul_ok(std::uint64_t a, std::uint64_t b, std::uint64_t& r) {
  return !__builtin_mul_overflow(a, b, &r);
}
inline bool add_ok(std::uint64_t a, std::uint64_t b, std::uint64_t& r) {
  return !__builtin_add_overflow(a, b, &r);
}

// Payload size implied by the counts; false on overflow.
inline bool payload_size(const SnapshotHeader& h, std::uint64_t& out) {
  std::uint64_t D = static_cast<std::uint64_t>(h.dim);
  std::uint64_t pts, ids = 0, cells, vals, tmp, total = 0;
  if (!mul_ok(h.n_vertices, D, tmp) || !mul_ok(tmp, 8, pts)) return false;
  if (!mul_ok(h.n_vertices, 8, ids)) return false;
  if (!mul_ok(h.n_cells, D + 1, tmp) || !mul_ok(tmp, 8, cells)) return false;  // 2 x u32
  if (!mul_ok(h.n_vertices, h.n_channels, tmp) || !mul_ok(tmp, 8, vals)) return false;
  std::uint64_t vcells = 0;
  if (h.n_cells && (!add_ok(h.n_vertices, 1, tmp) || !mul_ok(tmp, 4, vcells))) return false;
  if (!add_ok(total, pts, total) || !add_ok(total, ids, total) || !add_ok(total, cells, total) ||
      !add_ok(total, vcells, total) || !add_ok(total, vals, total))
    return false;
  out = total;
  return true;
}

constexpr int kMaxSnapshotDim = 64;

inline SnapshotHeader decode_header(Source& src) {
  unsigned char raw[kHeaderSize];
  src.read(raw, kHeaderSize, "the header");
  if (std::memcmp(raw, kSnapshotMagic, 8) != 0)
    throw snapshot_error("not a flatserve triangulation snapshot (bad magic)");
  std::uint32_t version, hsize;
  std::memcpy(&version, raw + 8, 4);
  std::memcpy(&hsize, raw + 12, 4);
  if (version != kSnapshotVersion)
    throw snapshot_error("unsupported snapshot version " + std::to_string(version) +
                         " (this build reads version " + std::to_string(kSnapshotVersion) + ")");
  if (hsize != kHeaderSize) throw snapshot_error("corrupted snapshot header (size)");
  std::uint64_t marker, hc;
  std::memcpy(&marker, raw + 64, 8);
  std::memcpy(&hc, raw + 72, 8);
  if (marker != kEndianMarker)
    throw snapshot_error("snapshot written on a machine of other byte order, or corrupted header");
  Checksum c;
  c.update(raw, 72);
  if (c.digest() != hc) throw snapshot_error("corrupted snapshot header (checksum mismatch)");
  SnapshotHeader h;
  std::memcpy(&h.dim, raw + 16, 4);
  std::memcpy(&h.current_dim, raw + 20, 4);
  std::memcpy(&h.n_vertices, raw + 24, 8);
  std::memcpy(&h.n_cells, raw + 32, 8);
  std::memcpy(&h.n_channels, raw + 40, 8);
  std::memcpy(&h.payload_bytes, raw + 48, 8);
  std::memcpy(&h.payload_checksum, raw + 56, 8);
  if (h.dim < 1 || h.dim > kMaxSnapshotDim || h.current_dim < -1 || h.current_dim > h.dim)
    throw snapshot_error("corrupted snapshot header (dimensions)");
  if (h.current_dim < h.dim && h.n_cells != 0)
    throw snapshot_error("corrupted snapshot header (cells in a degenerate triangulation)");
  if (h.n_cells > 0xffffffffull || h.n_vertices >= 0xffffffffull)
    throw snapshot_error("corrupted snapshot header (counts)");
  std::uint64_t expect;
  if (!payload_size(h, expect) || expect != h.payload_bytes)
    throw snapshot_error("corrupted snapshot header (payload size does not match the counts)");
  if (src.remaining() < h.payload_bytes)
    throw snapshot_error("snapshot truncated: header announces " + std::to_string(h.payload_bytes) +
                         " payload bytes, " + std::to_string(src.remaining()) + " present");
  return h;
}

}  // namespace flatserve

// Fixed-rate feedforward controller running an exported torchhys compensator.
//
//   controller MODEL REF.csv OUT.csv [--rate HZ] [--format torchscript|aoti]
//
// MODEL is a TorchScript file from torchhys.deploy.export.to_torchscript (frozen here and run by
// its method step_explicit, the state kept in this program) or an AOTInductor package
// (.pt2) from torchhys.deploy.export.to_aoti (explicit state). Both carry the same metadata (the
// package's metadata, the TorchScript file's extra files): "state_spec" (the fresh state's
// dtypes and shapes, all zeros) and "counter" ("tensor:column" of the counter of held
// non-finite samples), read here. REF.csv holds the reference trajectory (desired displacement), one value
// per line in its first column; lines that do not start with a number (a header) are
// skipped. OUT.csv receives "y_ref,u" per sample. --rate HZ paces the loop with a steady
// clock (default 1000; 0 runs as fast as possible). Prints the per-sample step latency
// (median, p99, max, in microseconds) and the number of held non-finite samples.
#include <torch/script.h>
#include <torch/torch.h>
#include <torch/csrc/jit/runtime/graph_executor.h>

#ifdef TORCHHYS_AOTI
#include <torch/csrc/inductor/aoti_package/model_package_loader.h>
#endif

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

namespace {

using Clock = std::chrono::steady_clock;

std::vector<double> read_reference(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open reference file " + path);
  std::vector<double> ref;
  std::string line;
  while (std::getline(in, line)) {
    std::string first = line.substr(0, line.find(','));
    char* end = nullptr;
    double v = std::strtod(first.c_str(), &end);
    if (end == first.c_str()) continue;  // header or empty line
    ref.push_back(v);
  }
  return ref;
}

// "tensor:column" of the metadata's "counter" entry.
std::pair<size_t, int64_t> parse_position(const std::string& text) {
  auto colon = text.find(':');
  if (colon == std::string::npos) throw std::runtime_error("bad position in metadata: " + text);
  return {std::stoul(text.substr(0, colon)), std::stoll(text.substr(colon + 1))};
}

// One compensator behind a common interface: step(x) -> u for a batch of one.
struct Stepper {
  virtual ~Stepper() = default;
  virtual double step(double x) = 0;
  // the held non-finite samples: the state tensor and column named by "counter"
  virtual int64_t nonfinite() = 0;
};

// Reads element 0 of a float32/float64 tensor without a dispatched op (item() is one).
double first_value(const at::Tensor& t) {
  return t.scalar_type() == at::kFloat ? double(t.const_data_ptr<float>()[0])
                                       : t.const_data_ptr<double>()[0];
}

// Writes x into a one-element tensor of its dtype without a dispatched op.
void set_value(at::Tensor& t, double x) {
  if (t.scalar_type() == at::kFloat) t.mutable_data_ptr<float>()[0] = static_cast<float>(x);
  else t.mutable_data_ptr<double>()[0] = x;
}

// The TorchScript module, frozen (its weights and settings become constants, the branches
// on them are folded away) and run through its explicit-state method: the state list is
// kept here, so a step is one call of step_explicit without the attribute reads and
// writes and the argument checks of step().
struct ScriptStepper : Stepper {
  torch::jit::Module module;
  std::optional<torch::jit::Method> step_method;  // looked up once, not per sample
  c10::IValue state;                              // the state list (see "state_spec")
  at::ScalarType dtype;
  std::pair<size_t, int64_t> counter;
  explicit ScriptStepper(const std::string& path) {
    torch::jit::ExtraFilesMap extra{{"counter", ""}};
    torch::jit::Module loaded = torch::jit::load(path, c10::nullopt, extra);
    counter = parse_position(extra.at("counter"));
    loaded.eval();
    dtype = loaded.attr("low").toTensor().scalar_type();
    state = loaded.get_method("initial_state")({int64_t(1)});
    module = torch::jit::freeze(
        loaded, std::vector<std::string>{"step_explicit", "initial_state"},
        /*optimize_numerics=*/false);
    step_method = module.get_method("step_explicit");
  }
  double step(double x) override {
    // a fresh input each sample: the new state may keep a reference to it
    at::Tensor xt = at::empty({1}, at::TensorOptions().dtype(dtype));
    set_value(xt, x);
    c10::IValue out = (*step_method)({xt, state});
    const auto& elems = out.toTupleRef().elements();
    state = elems[1];
    return first_value(elems[0].toTensor());
  }
  int64_t nonfinite() override {
    return state.toTensorList().get(counter.first).select(1, counter.second).sum().item<int64_t>();
  }
};

#ifdef TORCHHYS_AOTI
at::ScalarType parse_dtype(const std::string& name) {
  if (name == "bool") return at::kBool;
  if (name == "int64") return at::kLong;
  if (name == "float32") return at::kFloat;
  if (name == "float64") return at::kDouble;
  throw std::runtime_error("unknown dtype in state_spec: " + name);
}

struct AotiStepper : Stepper {
  std::unique_ptr<torch::inductor::AOTIModelPackageLoader> loader;
  std::vector<at::Tensor> inputs;  // [x, state...]
  at::ScalarType dtype;
  std::pair<size_t, int64_t> counter;
  // single-threaded runner: this loop is the only caller, so the container's locking and
  // runner pool are skipped
  explicit AotiStepper(const std::string& path)
      : loader(std::make_unique<torch::inductor::AOTIModelPackageLoader>(path, "model", true)) {
    auto meta = loader->get_metadata();
    dtype = parse_dtype(meta.at("dtype"));
    counter = parse_position(meta.at("counter"));
    inputs.push_back(torch::zeros({1}, torch::TensorOptions().dtype(dtype)));
    std::stringstream spec(meta.at("state_spec"));
    std::string part;
    while (std::getline(spec, part, ';')) {
      auto colon = part.find(':');
      std::vector<int64_t> shape;
      std::stringstream dims(part.substr(colon + 1));
      std::string d;
      while (std::getline(dims, d, ',')) shape.push_back(std::stoll(d));
      inputs.push_back(
          torch::zeros(shape, torch::TensorOptions().dtype(parse_dtype(part.substr(0, colon)))));
    }
  }
  double step(double x) override {
    set_value(inputs[0], x);
    // boxed_run takes the inputs over (no handle copies); the input buffer is kept by
    // reference, the state tensors are replaced by the returned ones
    std::vector<at::Tensor> args;
    args.reserve(inputs.size());
    args.push_back(inputs[0]);
    for (size_t i = 1; i < inputs.size(); ++i) args.push_back(std::move(inputs[i]));
    std::vector<at::Tensor> out = loader->boxed_run(std::move(args));
    for (size_t i = 1; i < out.size(); ++i) inputs[i] = std::move(out[i]);
    return first_value(out[0]);
  }
  int64_t nonfinite() override {  // inputs = [x, state...]
    return inputs[1 + counter.first].select(1, counter.second).sum().item<int64_t>();
  }
};
#endif

bool ends_with(const std::string& s, const std::string& suffix) {
  return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 4) {
    std::cerr << "usage: " << argv[0]
              << " MODEL REF.csv OUT.csv [--rate HZ] [--format torchscript|aoti]\n";
    return 2;
  }
  std::string model_path = argv[1], ref_path = argv[2], out_path = argv[3];
  double rate = 1000.0;
  std::string format = ends_with(model_path, ".pt2") ? "aoti" : "torchscript";
  for (int i = 4; i + 1 < argc; i += 2) {
    std::string opt = argv[i];
    if (opt == "--rate") rate = std::atof(argv[i + 1]);
    else if (opt == "--format") format = argv[i + 1];
    else { std::cerr << "unknown option " << opt << "\n"; return 2; }
  }
  try {
    at::set_num_threads(1);
    // InferenceMode skips autograd and version-counter bookkeeping on every tensor op.
    c10::InferenceMode inference_mode;
    if (const char* mode = std::getenv("TORCHHYS_JIT_PROFILING")) {
      // 0: the simple graph executor (no profiling runs, no type guards); 1: the default
      bool on = std::string(mode) != "0";
      torch::jit::getProfilingMode() = on;
      torch::jit::getExecutorMode() = on;
    }
    std::unique_ptr<Stepper> stepper;
    if (format == "torchscript") {
      stepper = std::make_unique<ScriptStepper>(model_path);
    } else if (format == "aoti") {
#ifdef TORCHHYS_AOTI
      stepper = std::make_unique<AotiStepper>(model_path);
#else
      std::cerr << "this controller was built without AOTInductor support\n";
      return 2;
#endif
    } else {
      std::cerr << "unknown format " << format << "\n";
      return 2;
    }
    std::vector<double> ref = read_reference(ref_path);
    std::vector<double> cmd(ref.size());
    std::vector<double> latency_us(ref.size());
    const auto period = rate > 0 ? std::chrono::duration_cast<Clock::duration>(
                                       std::chrono::duration<double>(1.0 / rate))
                                 : Clock::duration::zero();
    auto next = Clock::now();
    for (size_t t = 0; t < ref.size(); ++t) {
      if (rate > 0) {
        std::this_thread::sleep_until(next);
        next += period;
      }
      auto t0 = Clock::now();
      cmd[t] = stepper->step(ref[t]);
      auto t1 = Clock::now();
      latency_us[t] = std::chrono::duration<double, std::micro>(t1 - t0).count();
    }
    std::FILE* out = std::fopen(out_path.c_str(), "w");
    if (!out) throw std::runtime_error("cannot write " + out_path);
    std::fprintf(out, "y_ref,u\n");
    for (size_t t = 0; t < ref.size(); ++t) std::fprintf(out, "%.17g,%.17g\n", ref[t], cmd[t]);
    std::fclose(out);
    std::vector<double> sorted = latency_us;
    std::sort(sorted.begin(), sorted.end());
    auto pct = [&](double q) {
      return sorted.empty() ? 0.0 : sorted[std::min(sorted.size() - 1, size_t(q * sorted.size()))];
    };
    std::printf("format %s samples %zu median_us %.3f p99_us %.3f max_us %.3f nonfinite %lld\n",
                format.c_str(), ref.size(), pct(0.5), pct(0.99),
                sorted.empty() ? 0.0 : sorted.back(), (long long)stepper->nonfinite());
  } catch (const std::exception& e) {
    std::cerr << "error: " << e.what() << "\n";
    return 1;
  }
  return 0;
}

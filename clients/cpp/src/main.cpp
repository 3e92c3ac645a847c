// A minimal C++ learner against a tamrm server: creates a task, opens a Shape stream for
// a vector of corridor environments, sends one StepBatch per vector step and learns from
// the shaped rewards it gets back. Its last line is
//
//     episodes E pool_size P pool_version V
//
// E: the episodes this learner ended; P: the task's pool size after the stream closed
// (GetTask); V: the pool version of the last ShapedBatch.
//
// Usage: tamrm_learner ADDR [--task ID] [--envs N] [--steps N] [--seed N]
// Any non-OK gRPC status is printed with its code and message, and the exit code is 1.
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cstdint>
#include <cstdlib>
#include <deque>
#include <iomanip>
#include <iterator>
#include <iostream>
#include <memory>
#include <numeric>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "corridor.hpp"
#include "tamrm/v1/shaping.grpc.pb.h"

namespace {

namespace v1 = tamrm::v1;

struct Options {
    std::string address;
    std::string task_id;
    uint32_t envs = 8;
    uint32_t steps = 2000;
    uint64_t seed = 1;
};

constexpr uint32_t kCorridorLength = 12;
constexpr double kGamma = 0.99;
constexpr double kLearningRate = 0.2;
constexpr double kEpsilon = 0.1;

[[noreturn]] void usage(const std::string& problem) {
    std::cerr << "tamrm_learner: " << problem << "\n"
              << "usage: tamrm_learner ADDR [--task ID] [--envs N] [--steps N] [--seed N]\n";
    std::exit(2);
}

uint64_t parse_number(const std::string& flag, const std::string& text, uint64_t min) {
    try {
        size_t used = 0;
        const unsigned long long value = std::stoull(text, &used);
        if (used == text.size() && text[0] != '-' && value >= min) {
            return value;
        }
    } catch (const std::exception&) {
    }
    usage(flag + " takes an integer >= " + std::to_string(min) + ", got '" + text + "'");
}

Options parse(int argc, char** argv) {
    Options o;
    std::vector<std::string> args(argv + 1, argv + argc);
    for (size_t i = 0; i < args.size(); ++i) {
        const std::string& a = args[i];
        if (a == "-h" || a == "--help") {
            usage("a learner on a 1-D corridor, shaped by a tamrm server at ADDR");
        }
        if (a.rfind("--", 0) == 0) {
            if (i + 1 >= args.size()) {
                usage(a + " needs a value");
            }
            const std::string& value = args[++i];
            if (a == "--task") {
                o.task_id = value;
            } else if (a == "--envs") {
                o.envs = static_cast<uint32_t>(parse_number(a, value, 1));
            } else if (a == "--steps") {
                o.steps = static_cast<uint32_t>(parse_number(a, value, 1));
            } else if (a == "--seed") {
                o.seed = parse_number(a, value, 0);
            } else {
                usage("unknown option " + a);
            }
        } else if (o.address.empty()) {
            o.address = a;
        } else {
            usage("unexpected argument '" + a + "'");
        }
    }
    if (o.address.empty()) {
        usage("the server address (host:port) is missing");
    }
    if (o.task_id.empty()) {
        std::ostringstream id;
        id << "examples/cpp/" << std::hex << std::random_device{}() << std::random_device{}();
        o.task_id = id.str();
    }
    return o;
}

/// The status code's name as in the gRPC docs (gRPC C++ has no function for it).
const char* code_name(grpc::StatusCode code) {
    static const char* const names[] = {
        "OK",
        "CANCELLED",
        "UNKNOWN",
        "INVALID_ARGUMENT",
        "DEADLINE_EXCEEDED",
        "NOT_FOUND",
        "ALREADY_EXISTS",
        "PERMISSION_DENIED",
        "RESOURCE_EXHAUSTED",
        "FAILED_PRECONDITION",
        "ABORTED",
        "OUT_OF_RANGE",
        "UNIMPLEMENTED",
        "INTERNAL",
        "UNAVAILABLE",
        "DATA_LOSS",
        "UNAUTHENTICATED",
    };
    const auto i = static_cast<size_t>(code);
    return i < std::size(names) ? names[i] : "UNRECOGNIZED";
}

/// Prints a failed call's status (code and the server's message) and exits with 1.
[[noreturn]] void fail(const std::string& call, const grpc::Status& status) {
    std::cerr << "tamrm_learner: " << call << " failed: " << code_name(status.error_code())
              << ": " << status.error_message() << "\n";
    std::exit(1);
}

[[noreturn]] void protocol_error(const std::string& what) {
    std::cerr << "tamrm_learner: unexpected answer from the server: " << what << "\n";
    std::exit(1);
}

/// A unary call's context with a deadline (a stream has none: it lives as long as the run).
std::unique_ptr<grpc::ClientContext> unary_context() {
    auto ctx = std::make_unique<grpc::ClientContext>();
    ctx->set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    return ctx;
}

v1::Task create_task(v1::Shaping::Stub& stub, const std::string& task_id) {
    v1::CreateTaskRequest req;
    req.set_task_id(task_id);
    v1::TaskConfig* config = req.mutable_config();
    config->set_num_actions(corridor::kNumActions);
    config->set_pool_capacity(16);
    config->set_k(4);
    config->set_start_step(2);
    config->set_min_pool_size(4);
    config->set_gamma(kGamma);
    v1::Task task;
    const grpc::Status status = stub.CreateTask(unary_context().get(), req, &task);
    if (!status.ok()) {
        fail("CreateTask", status);
    }
    return task;
}

v1::Task get_task(v1::Shaping::Stub& stub, const std::string& task_id) {
    v1::GetTaskRequest req;
    req.set_task_id(task_id);
    v1::Task task;
    const grpc::Status status = stub.GetTask(unary_context().get(), req, &task);
    if (!status.ok()) {
        fail("GetTask", status);
    }
    return task;
}

using ShapeStream = grpc::ClientReaderWriter<v1::ShapeRequest, v1::ShapeResponse>;

/// A broken stream (a failed Write or Read) ends with the status the server sent.
[[noreturn]] void stream_broke(ShapeStream& stream) {
    fail("Shape", stream.Finish());
}

v1::ShapeResponse exchange(ShapeStream& stream, const v1::ShapeRequest& req) {
    v1::ShapeResponse resp;
    if (!stream.Write(req) || !stream.Read(&resp)) {
        stream_broke(stream);
    }
    return resp;
}

}  // namespace

int main(int argc, char** argv) {
    const Options opt = parse(argc, argv);
    auto channel = grpc::CreateChannel(opt.address, grpc::InsecureChannelCredentials());
    auto stub = v1::Shaping::NewStub(channel);

    const v1::Task task = create_task(*stub, opt.task_id);
    std::cout << "task " << task.task_id() << " (k " << task.config().k() << ", alpha "
              << task.config().alpha() << ", beta " << task.config().beta() << ")\n";

    std::vector<corridor::Env> envs;
    for (uint32_t i = 0; i < opt.envs; ++i) {
        envs.emplace_back(kCorridorLength, opt.seed * 1000 + i);
    }
    corridor::QTable q(kCorridorLength, opt.seed);

    grpc::ClientContext stream_ctx;
    std::unique_ptr<ShapeStream> stream = stub->Shape(&stream_ctx);
    v1::ShapeRequest open;
    open.mutable_open()->set_task_id(task.task_id());
    open.mutable_open()->set_num_envs(opt.envs);
    if (exchange(*stream, open).kind_case() != v1::ShapeResponse::kOpened) {
        protocol_error("the first answer is not `opened`");
    }

    uint64_t episodes = 0;
    uint64_t pool_version = 0;
    std::vector<double> returns(opt.envs, 0.0);
    std::deque<double> recent;  // the last 100 episode returns, for the progress lines
    std::vector<uint32_t> states(opt.envs);
    std::vector<corridor::Step> outcomes(opt.envs);
    v1::ShapeRequest req;
    for (uint32_t t = 1; t <= opt.steps; ++t) {
        // One entry per environment, in env order (env_ids left empty: entry i is env i).
        v1::StepBatch* batch = req.mutable_steps();
        batch->Clear();
        for (uint32_t i = 0; i < opt.envs; ++i) {
            states[i] = envs[i].state();
            const uint32_t action = q.act(states[i], kEpsilon);
            outcomes[i] = envs[i].step(action);
            batch->add_actions(action);
            batch->add_rewards(outcomes[i].reward);
            batch->add_terminated(outcomes[i].terminated);
            batch->add_truncated(outcomes[i].truncated);
            for (float v : q.values(states[i])) {
                batch->add_q_values(v);
            }
            for (float v : q.values(outcomes[i].next_state)) {
                batch->add_next_q_values(v);
            }
        }
        const v1::ShapeResponse resp = exchange(*stream, req);
        if (resp.kind_case() != v1::ShapeResponse::kShaped ||
            static_cast<uint32_t>(resp.shaped().rewards_size()) != opt.envs) {
            protocol_error("batch " + std::to_string(t) + " is not answered by one `shaped` with " +
                           std::to_string(opt.envs) + " rewards");
        }
        const v1::ShapedBatch& shaped = resp.shaped();
        pool_version = shaped.pool_version();
        for (uint32_t i = 0; i < opt.envs; ++i) {
            const corridor::Step& out = outcomes[i];
            const int entry = static_cast<int>(i);
            q.learn(states[i], batch->actions(entry), shaped.rewards(entry), out.next_state,
                    out.terminated, kGamma, kLearningRate);
            returns[i] += out.reward;
            if (out.terminated || out.truncated) {
                episodes += 1;
                recent.push_back(returns[i]);
                if (recent.size() > 100) {
                    recent.pop_front();
                }
                returns[i] = 0.0;
                envs[i].reset();
            }
        }
        if (t % 500 == 0 || t == opt.steps) {
            const double sum = std::accumulate(recent.begin(), recent.end(), 0.0);
            const double mean = recent.empty() ? 0.0 : sum / static_cast<double>(recent.size());
            std::cout << "step " << t << "/" << opt.steps << " episodes " << episodes
                      << " mean_return(last 100) " << std::fixed << std::setprecision(4) << mean
                      << std::defaultfloat << " pool_version " << pool_version << "\n";
        }
    }

    // Half-close: the server ends the stream with OK once it has answered every batch.
    stream->WritesDone();
    v1::ShapeResponse extra;
    if (stream->Read(&extra)) {
        protocol_error("an answer after the last batch");
    }
    const grpc::Status closed = stream->Finish();
    if (!closed.ok()) {
        fail("Shape", closed);
    }

    const v1::Task after = get_task(*stub, task.task_id());
    std::cout << "episodes " << episodes << " pool_size " << after.stats().pool_size()
              << " pool_version " << pool_version << std::endl;
    return 0;
}

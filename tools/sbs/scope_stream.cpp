#include "scope_stream.hpp"

#include <nlohmann/json.hpp>

#include <pthread.h>
#include <sched.h>

#include <algorithm>

namespace chimera::cli {

ScopeStream::ScopeStream(std::string rmod, const std::string& ring, Send send, ScopeSettings settings)
    : rmod_(std::move(rmod)),
      reader_(sampler::RingReader::attach(ring)),
      send_(std::move(send)),
      settings_(bounded(settings, reader_.channels())),
      numbers_(settings_.max_batch),
      time_ns_(settings_.max_batch),
      cycles_(settings_.max_batch),
      values_(settings_.max_batch * reader_.channels()) {
    reader_.rewind();  // from the task's first sample: the page misses none
}

// Fewer samples per batch when there are many channels: one message stays small.
ScopeSettings ScopeStream::bounded(ScopeSettings s, std::size_t channels) {
    s.max_batch = std::max<std::size_t>(1, std::min(s.max_batch, s.max_values / std::max<std::size_t>(1, channels)));
    return s;
}

void ScopeStream::start() {
    std::lock_guard lock(mu_);
    if (!thread_.joinable() && !stopping_) thread_ = std::thread([this] { run(); });
}

ScopeStream::~ScopeStream() { stop(); }

void ScopeStream::ack(std::uint64_t batch) {
    {
        std::lock_guard lock(mu_);
        if (batch <= acked_ || batch > sent_) return;  // a batch not sent yet is no acknowledgement
        for (; acked_ < batch; ++acked_) {
            unacked_bytes_ -= unacked_sizes_.front();
            unacked_sizes_.pop_front();
        }
    }
    wake_.notify_all();
}

void ScopeStream::stop() {
    {
        std::lock_guard lock(mu_);
        stopping_ = true;
    }
    wake_.notify_all();
    if (thread_.joinable()) thread_.join();
}

void ScopeStream::run() {
    sched_param sp{};
    ::pthread_setschedparam(::pthread_self(), SCHED_OTHER, &sp);  // never competes with the tasks
    std::unique_lock lock(mu_);
    while (!stopping_) {
        // Send while the page keeps up, then sleep a period (or until an ack).
        while (!stopping_ && sent_ - acked_ < settings_.window && unacked_bytes_ < settings_.max_unacked_bytes) {
            lock.unlock();
            const bool sent = send_batch();
            lock.lock();
            if (!sent) break;
        }
        if (closed_sent_) break;
        wake_.wait_for(lock, settings_.period, [&] { return stopping_; });
    }
}

// One sample at a time, so each carries its ring number even when the writer
// laps this reader in the middle of a batch.
ScopeStream::Taken ScopeStream::take() {
    Taken got;
    while (got.samples < settings_.max_batch) {
        const std::size_t k = got.samples;
        const sampler::ReadCount c =
            reader_.read(&time_ns_[k], &cycles_[k], &values_[k * reader_.channels()], 1);
        got.lost += c.lost;
        if (c.samples == 0) break;
        numbers_[k] = reader_.position() - 1;
        ++got.samples;
    }
    return got;
}

bool ScopeStream::send_batch() {
    const Taken got = take();
    // The writer finished and every sample was sent: one last batch says so.
    const bool closing = got.samples == 0 && got.lost == 0 && reader_.closed() && reader_.position() == reader_.head();
    if (got.samples == 0 && got.lost == 0 && (!closing || closed_sent_)) return false;
    closed_sent_ = closing;
    if (got.samples > 0 && !have_origin_) {
        origin_ns_ = time_ns_[0];
        have_origin_ = true;
    }
    const std::string text = batch_text(got, closing);
    {
        std::lock_guard lock(mu_);
        ++sent_;
        unacked_sizes_.push_back(text.size());
        unacked_bytes_ += text.size();
    }
    send_(text);
    return !closing;
}

std::string ScopeStream::batch_text(const Taken& got, bool closing) {
    const std::size_t samples = got.samples;
    const std::size_t width = reader_.channels();
    nlohmann::json n = nlohmann::json::array(), t = nlohmann::json::array(), cycle = nlohmann::json::array(),
                   values = nlohmann::json::array();
    for (std::size_t k = 0; k < samples; ++k) {
        n.push_back(numbers_[k]);
        t.push_back(time_ns_[k] - origin_ns_);
        cycle.push_back(cycles_[k]);
    }
    for (std::size_t i = 0; i < width; ++i) {
        nlohmann::json column = nlohmann::json::array();
        for (std::size_t k = 0; k < samples; ++k) column.push_back(values_[k * width + i]);
        values.push_back(std::move(column));
    }
    const nlohmann::json data = {{"rmod", rmod_},       {"batch", sent_ + 1},        {"n", std::move(n)},
                                 {"t", std::move(t)},   {"cycle", std::move(cycle)}, {"values", std::move(values)},
                                 {"lost", got.lost},    {"lost_total", reader_.lost_total()},
                                 {"closed", closing}};
    return nlohmann::json({{"stream", "scope"}, {"data", data}})
        .dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
}

}  // namespace chimera::cli

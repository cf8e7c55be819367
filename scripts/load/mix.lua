-- wrk script: a mix of valid and invalid `slag-edge serve` queries, round robin per thread.
-- Counts responses by status class and prints them per run (wrk >= 4.0 Lua API).
local valid = {
  "/query?text=red",
  "/query?text=a%20green%20chair&top_k=10",
  "/query?text=blue&mode=relevancy",
  "/query?text=gray&threshold=none&top_k=1000",
  "/query?text=pink&bbox=0,0,0,1000,1000,10",
  "/stats",
}
local invalid = {
  "/query",
  "/query?text=red&top_k=0",
  "/query?text=red&threshold=nan",
  "/query?text=red&bbox=1,2",
}
local paths = {}
for _, p in ipairs(valid) do paths[#paths + 1] = p end
for _, p in ipairs(invalid) do paths[#paths + 1] = p end

local threads = {}
function setup(thread)
  table.insert(threads, thread)
end

function init(args)
  i = 0
  s2, s4, s5, other = 0, 0, 0, 0
end

function request()
  i = i + 1
  return wrk.format("GET", paths[(i % #paths) + 1])
end

function response(status, headers, body)
  if status >= 200 and status < 300 then s2 = s2 + 1
  elseif status >= 400 and status < 500 then s4 = s4 + 1
  elseif status >= 500 then s5 = s5 + 1
  else other = other + 1 end
end

function done(summary, latency, requests)
  local a2, a4, a5, ao = 0, 0, 0, 0
  for _, t in ipairs(threads) do
    a2 = a2 + t:get("s2"); a4 = a4 + t:get("s4"); a5 = a5 + t:get("s5"); ao = ao + t:get("other")
  end
  io.write(string.format("STATUS 2xx=%d 4xx=%d 5xx=%d other=%d (invalid share of the mix %.2f)\n",
    a2, a4, a5, ao, #invalid / #paths))
  io.write(string.format("LATENCY_MS p50=%.1f p90=%.1f p99=%.1f max=%.1f\n",
    latency:percentile(50) / 1000, latency:percentile(90) / 1000, latency:percentile(99) / 1000,
    latency.max / 1000))
  io.write(string.format("RPS %.2f over %.1f s, errors connect=%d read=%d write=%d timeout=%d\n",
    summary.requests / (summary.duration / 1e6), summary.duration / 1e6,
    summary.errors.connect, summary.errors.read, summary.errors.write, summary.errors.timeout))
end

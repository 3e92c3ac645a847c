-- The pool update of SPEC §6 for a commit (of one request, or of a group of them: their
-- operations one after the other), decided against the pool in Redis, atomically.
--
-- KEYS: meta, traj, scores, then the end record of each client whose episode ends the
-- commit carries (a group may carry several clients').
-- ARGV: incarnation, channel, task key, Δepisodes, Δsteps, end-record TTL (s), number of
-- ops, then 6 per op: kind ('offer' / 'reset'), score, trajectory bytes, env, episodes
-- ended with this one (the episode's number + 1, saturating), and which of the end
-- records it goes to (1-based among them); env, count and record are '' for no record.
-- Answers {1, version before, version after, next_seq before, then per op 1 changed /
-- 0 not / 2 a re-sent end}, or {0} if this incarnation of the task is gone.
--
-- §6: while the pool holds fewer than `capacity` trajectories an offer is inserted;
-- when it is full, it replaces the lowest score (the lowest seq among equal scores) if
-- its score is strictly greater, else it is discarded. Every change takes the next seq
-- and bumps the version; a reset empties the pool and bumps the version.
--
-- Episode counts are u64 in decimal, compared as such (`at_least`): Lua's numbers are
-- doubles, exact only below 2^53.
local function at_least(a, b)
  if #a ~= #b then return #a > #b end
  return a >= b
end
if redis.call('HGET', KEYS[1], 'incarnation') ~= ARGV[1] then return {0} end
local m = redis.call('HMGET', KEYS[1], 'capacity', 'version', 'next_seq')
local cap, version, next_seq = tonumber(m[1]), tonumber(m[2]), tonumber(m[3])
local before, seq_before = version, next_seq
local out = {1, before, 0, seq_before}
local marked = {}
local resent = 0
local i = 8
for op = 1, tonumber(ARGV[7]) do
  local kind = ARGV[i]
  local changed = 0
  if kind == 'reset' then
    redis.call('DEL', KEYS[2], KEYS[3])
    version = version + 1
    changed = 1
  else
    local score, env, count = tonumber(ARGV[i + 1]), ARGV[i + 3], ARGV[i + 4]
    local record = nil
    if env ~= '' then record = 3 + tonumber(ARGV[i + 5]) end
    local dup = false
    if record then
      local n = redis.call('HGET', KEYS[record], env)
      dup = n ~= false and at_least(n, count)
    end
    if dup then
      changed = 2
      resent = resent + 1
    else
      local size = redis.call('HLEN', KEYS[3])
      local replaces = nil
      local insert = size < cap
      if not insert then
        local all = redis.call('HGETALL', KEYS[3])
        local worst, worst_seq = nil, nil
        for j = 1, #all, 2 do
          local s, q = tonumber(all[j + 1]), tonumber(all[j])
          if worst == nil or s < worst or (s == worst and q < worst_seq) then
            worst, worst_seq = s, q
          end
        end
        if score > worst then
          insert, replaces = true, worst_seq
        end
      end
      if insert then
        if replaces then
          redis.call('HDEL', KEYS[2], replaces)
          redis.call('HDEL', KEYS[3], replaces)
        end
        redis.call('HSET', KEYS[2], next_seq, ARGV[i + 2])
        redis.call('HSET', KEYS[3], next_seq, ARGV[i + 1])
        next_seq = next_seq + 1
        version = version + 1
        changed = 1
      end
      if record then
        redis.call('HSET', KEYS[record], env, count)
        marked[record] = true
      end
    end
  end
  out[#out + 1] = changed
  i = i + 6
end
redis.call('HSET', KEYS[1], 'version', version, 'next_seq', next_seq)
-- Δepisodes counted the re-sent ends too: they are not episodes completed.
redis.call('HINCRBY', KEYS[1], 'episodes_completed', math.max(0, tonumber(ARGV[4]) - resent))
redis.call('HINCRBY', KEYS[1], 'steps_shaped', ARGV[5])
for record in pairs(marked) do redis.call('EXPIRE', KEYS[record], ARGV[6]) end
if version ~= before then
  redis.call('PUBLISH', ARGV[2], version .. ' ' .. ARGV[1] .. ' ' .. ARGV[3])
end
out[3] = version
return out

-- Takes step tokens from a tenant's bucket, which refills at `rate` tokens per second
-- (by Redis's clock, the one clock of every replica) up to `rate`.
-- KEYS: the tenant's bucket (a hash: tokens, at = the time of its last change in µs).
-- ARGV: rate, need, want.
-- Answers how many tokens it took: want if the bucket holds them, else all it holds if
-- that is at least need (whole tokens), else 0 (and nothing taken).
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000000 + tonumber(t[2])
local rate, need, want = tonumber(ARGV[1]), tonumber(ARGV[2]), tonumber(ARGV[3])
local b = redis.call('HMGET', KEYS[1], 'tokens', 'at')
-- No bucket (new, or idle long enough to expire): a full one.
local tokens = tonumber(b[1]) or rate
local at = tonumber(b[2]) or now
if now > at then
  tokens = math.min(rate, tokens + (now - at) * rate / 1000000)
end
local took = 0
if tokens >= need then
  took = math.min(want, math.floor(tokens))
  tokens = tokens - took
end
redis.call('HSET', KEYS[1], 'tokens', string.format('%.6f', tokens), 'at', string.format('%d', now))
-- A bucket refills in a second at most: after two idle ones it is full, as no bucket is.
redis.call('PEXPIRE', KEYS[1], 2000)
return took

-- Takes a lease on one of a tenant's open streams unless the tenant holds max live ones.
-- KEYS: the tenant's lease set (a sorted set: member = lease id, score = its expiry in
-- ms of Redis's clock). ARGV: lease id, max, lease time in ms.
-- Answers 1 (taken) or 0 (max live leases held). Expired leases are dropped first.
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
redis.call('ZREMRANGEBYSCORE', KEYS[1], '-inf', now)
if redis.call('ZCARD', KEYS[1]) >= tonumber(ARGV[2]) then
  return 0
end
local expiry = now + tonumber(ARGV[3])
redis.call('ZADD', KEYS[1], expiry, ARGV[1])
-- The set outlives its last lease by nothing: a tenant whose replicas all died leaves
-- no key behind.
local last = redis.call('ZRANGE', KEYS[1], -1, -1, 'WITHSCORES')
redis.call('PEXPIREAT', KEYS[1], last[2])
return 1

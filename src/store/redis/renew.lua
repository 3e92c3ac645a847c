-- Renews a replica's live leases of one tenant: each expires a lease time from now.
-- A lease that expired meanwhile (the replica could not reach Redis for a lease time)
-- is added again: its stream is still open, and counts.
-- KEYS: the tenant's lease set. ARGV: lease time in ms, then the lease ids.
-- Answers the number of leases renewed.
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
local expiry = now + tonumber(ARGV[1])
for i = 2, #ARGV do
  redis.call('ZADD', KEYS[1], expiry, ARGV[i])
end
redis.call('ZREMRANGEBYSCORE', KEYS[1], '-inf', now)
local last = redis.call('ZRANGE', KEYS[1], -1, -1, 'WITHSCORES')
if last[2] then
  redis.call('PEXPIREAT', KEYS[1], last[2])
end
return #ARGV - 1

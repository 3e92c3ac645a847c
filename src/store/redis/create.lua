-- Creates the task unless one exists.
-- KEYS: meta, traj, scores. ARGV: config JSON, capacity, incarnation.
-- Answers {1 created / 0 existed, the stored config JSON, the stored incarnation}.
local existing = redis.call('HGET', KEYS[1], 'config')
if existing then
  return {0, existing, redis.call('HGET', KEYS[1], 'incarnation')}
end
redis.call('DEL', KEYS[2], KEYS[3])
redis.call('HSET', KEYS[1], 'config', ARGV[1], 'capacity', ARGV[2], 'version', 0,
  'next_seq', 1, 'incarnation', ARGV[3], 'episodes_completed', 0, 'steps_shaped', 0)
return {1, ARGV[1], ARGV[3]}

-- Deletes the task if it is the incarnation named and announces the deletion.
-- KEYS: meta, traj, scores. ARGV: incarnation, channel, task key.
-- Answers 1, or 0 if that incarnation is gone.
if redis.call('HGET', KEYS[1], 'incarnation') ~= ARGV[1] then return 0 end
redis.call('DEL', KEYS[1], KEYS[2], KEYS[3])
redis.call('PUBLISH', ARGV[2], 'deleted ' .. ARGV[1] .. ' ' .. ARGV[3])
return 1

-- Adds a task key to the index of every task unless its tenant holds max tasks there:
-- the task quota, checked and taken in one step by every replica.
-- KEYS: the task index (a set of task keys). ARGV: the task key, the tenant's key prefix
-- (`tenant@`; empty for the default tenant, whose keys are plain ids without `@`, see
-- task_key.rs), max.
-- Answers 1 (in the index: added now, or there already, which is no new task) or 0 (the
-- tenant holds max tasks).
if redis.call('SISMEMBER', KEYS[1], ARGV[1]) == 1 then
  return 1
end
local prefix, n = ARGV[2], 0
for _, key in ipairs(redis.call('SMEMBERS', KEYS[1])) do
  if prefix == '' then
    if not string.find(key, '@', 1, true) then
      n = n + 1
    end
  elseif string.sub(key, 1, #prefix) == prefix then
    n = n + 1
  end
end
if n >= tonumber(ARGV[3]) then
  return 0
end
redis.call('SADD', KEYS[1], ARGV[1])
return 1

"""Foundation used by every layer: errors, atomic files and hashing, executors, progress."""

"""Foundation used by every layer: errors, atomic files and hashing, file access that follows
no link inside an output folder and reads within a cap, executors, progress."""

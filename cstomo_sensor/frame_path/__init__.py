"""One sensor's frames from a source through the frame stream to its outputs: sources, the one loop, the stream and
its stages (mask, filter, noise in use, health), the per-frame pipeline, settings."""

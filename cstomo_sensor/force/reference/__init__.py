"""The device's reference: its files (reference frames, noise), the tare's rules and transaction, the first tare's
watch, the noise estimated from frames, the calibration on loads."""

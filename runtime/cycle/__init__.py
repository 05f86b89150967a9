"""The cycle process: one real-time thread running the drives, the machine and the setpoints."""

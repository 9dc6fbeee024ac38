"""Stand-ins for the lab's hardware: the UR controller emulator that the unmodified ur_rtde talks to
(:mod:`.ur_emulator`)."""

"""Stand-ins for the lab's hardware: the UR controller emulator that the unmodified ur_rtde talks to
(:mod:`.ur_emulator`: its sockets, sessions and dashboard), built from the RTDE protocol (:mod:`.rtde`), the
emulated arm (:mod:`.ur_arm`) and the controller that runs ur_rtde's control script (:mod:`.ur_controller`)."""

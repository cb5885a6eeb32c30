"""Running a day on this machine: the OS processes of its roles, started, watched and always stopped
(processes.py), and the process faults injected into them (faults.py)."""

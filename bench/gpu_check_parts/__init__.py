"""The parts of ``bench/gpu_check.py`` beside the script (its docstring says what each checks):
:mod:`.state`, Part 0, the process-wide state (cuBLAS's workspace, torch's flags, the loader
workers ``/dev/shm`` holds). ``bench/gpu_check.py`` puts ``bench/`` on the path.
"""

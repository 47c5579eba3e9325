"""The command line (`python -m app`) and its wiring."""
import os

# numpy's OpenBLAS keeps a helper thread per core busy-waiting for work for a while after each call. The stack's
# matrices are small, so the helpers gain nothing; they take the second core from the planner and the camera, and
# time.process_time (the CPU time per solve of `app bench`, and of each plan in a race) counts their spinning: on
# the 2-core machine the merge bench's median CPU time of RD3G on head-on 5 cars was 53.5 ms with them and 29.8 ms
# without (ALGames 141.9 and 80.7). One BLAS thread unless the user set it; this runs before numpy is imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

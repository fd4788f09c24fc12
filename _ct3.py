import time, sys
import numba
from numba.core import event as ev
@numba.njit
def _w(x): return x + 1.0
_w(1.0)
import planner.agent
stack=[]; excl={}; incl={}
class L(ev.Listener):
    def on_start(self, e):
        if e.kind == 'numba:compile': stack.append([e.data['dispatcher'].py_func.__name__, time.process_time(), 0.0])
    def on_end(self, e):
        if e.kind == 'numba:compile':
            name, t0, child = stack.pop(); dt = time.process_time() - t0
            excl[name] = excl.get(name, 0) + dt - child; incl[name] = incl.get(name, 0) + dt
            if stack: stack[-1][2] += dt
ev.register('numba:compile', L())
t = time.process_time()
import planner.node.warm
print('total', round(time.process_time() - t, 2))
for k, v in sorted(excl.items(), key=lambda x: -x[1])[:int(sys.argv[1]) if len(sys.argv) > 1 else 45]: print(f"{k:28s} self {v:6.2f}  incl {incl[k]:6.2f}")

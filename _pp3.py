import sys, time, importlib, numpy as np
import missions.study.simulator as S
from missions.study.simulator import RunSpec, _Simulation
from planner.sensing import SENSING
from planner import agent
from tests.simulator.conftest import paper_mission
name, K_at, modname = sys.argv[1], int(sys.argv[2]), sys.argv[3]
Kx = importlib.import_module(modname)
sim = _Simulation(RunSpec(paper_mission(name), "A", 20, K_at + 1), None, False, False, SENSING)
cap = {}
orig = S.plan
def spy(config, scene, state, **kw):
    cap.update(config=config, scene=scene, state=state, kw=kw); return orig(config, scene, state, **kw)
S.plan = spy
for k in range(K_at + 1): sim.step(k, None)
config, scene, state = cap['config'], cap['scene'], cap['state']
batch = scene.batch; B = int(np.prod(batch)); n = 10
p_hat = np.asarray(scene.estimate_m, float)
ks = agent._kernel_scene(scene, p_hat, batch, n); kc = agent._kernel_config(config, scene.step_index, False, False, n)
old = state.kernel_arrays(); new = tuple(np.empty_like(a) for a in old)
out = (np.empty((B, 3)), np.empty((B, 8), bool), np.empty((B, 1)))
roles = (np.ascontiguousarray(config.ranging), np.ascontiguousarray(config.bearing), False)
vl = agent.K.as_batch(scene.view_los, batch + (n,), bool, 1)
cost = (np.empty(B), np.empty((B, 3)), np.empty(B, np.int8))
f = lambda: Kx.plan_batch(ks, vl, roles, old, kc, new, out, cost, False)
f(); ts = []
for _ in range(40):
    t = time.perf_counter(); f(); ts.append(time.perf_counter() - t)
print(f"{modname} {name} k={K_at}: {min(ts)/B*1e6:.2f} us/drone (median {np.median(ts)/B*1e6:.2f})")

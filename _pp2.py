import sys, time, numpy as np
import missions.study.simulator as S
from missions.study.simulator import RunSpec, _Simulation
from planner.sensing import SENSING
from planner import kernels as K, agent
from tests.simulator.conftest import paper_mission
name, K_at = sys.argv[1], int(sys.argv[2])
sim = _Simulation(RunSpec(paper_mission(name), "A", 20, K_at + 1), None, False, False, SENSING)
cap = {}
orig = S.plan
def spy(config, scene, state, **kw):
    cap.update(config=config, scene=scene, state=state, kw=kw); return orig(config, scene, state, **kw)
S.plan = spy
for k in range(K_at + 1): sim.step(k, None)
config, scene, state, kw = cap['config'], cap['scene'], cap['state'], cap['kw']
B = int(np.prod(scene.batch))
def best(f, n=30):
    f(); ts = []
    for _ in range(n):
        t = time.perf_counter(); f(); ts.append(time.perf_counter() - t)
    return min(ts) / B * 1e6
r = orig(config, scene, state, **kw)
print(f"{name} k={K_at} B={B} filtered {r.step.filtered.mean():.1%} plan {best(lambda: orig(config, scene, state, **kw)):.2f} us/drone")
p = K.as_batch(scene.own_position_m, scene.batch + (3,), float, 1); ph = K.as_batch(scene.estimate_m, scene.batch + (3,), float, 1)
bmin, bmax = config.boxes_min_m, config.boxes_max_m
print(f"  own_los {best(lambda: K.own_los_batch(p, ph, np.ones(B, bool), True, bmin, bmax)):.2f}")
n = 10
vp = K.as_batch(scene.view_positions_m, scene.batch + (n, 3), float, 2); m = np.ones((B, n), bool); lw = np.ones((B, n))
J = np.zeros((B, 3, 3))
print(f"  fim {best(lambda: K.fim_batch(ph, vp, m, m, lw, config.channel.kernel_array, J)):.2f}")
out = np.empty((B, 14)); Jg = np.tile(np.eye(3) * 1e-3, (B, 1, 1)) + J
print(f"  grad {best(lambda: K.cost_gradient_batch(Jg, ph, p, np.ones(B, bool), np.ones(B, bool), np.ones(B), np.zeros((B, 3)), True, config.channel.kernel_array, False, out)):.2f}")
print(f"  infos: sigma {best(lambda: K.small_batch(K.as_batch(scene.information, scene.batch + (3, 3), float, 2), np.zeros((0, 3)))):.2f}")

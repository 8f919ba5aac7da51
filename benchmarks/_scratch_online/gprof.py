import time, numpy as np, jax, jax.numpy as jnp, functools, sys
from evojax_motion.online import *
from evojax_motion.basis import select_neighbours, pca_basis
from evojax_motion.ik import solve_ik
from evojax_motion.compile_interp import solve_boundary, Boundary
from evojax_motion.timegrid import derivatives
m = load_online_model("benchmarks/results/online_latency_db.npz")
dbj=m.db_device; dyn=m.dyn; grid=m.grid
lo,hi=[jnp.asarray(x,jnp.float32) for x in (m.robot.lower,m.robot.upper)]
B=int(sys.argv[1])
rng=np.random.default_rng(0); v=np.flatnonzero(m.db.valid)
tg=jnp.asarray(m.db.condition[v[rng.integers(0,len(v),B)]]+rng.normal(0,0.02,(B,3)).astype(np.float32))
def bench(name, f, *a):
    f=jax.jit(f); t=time.perf_counter(); jax.block_until_ready(f(*a)); c=time.perf_counter()-t
    ts=[]
    for i in range(5):
        t=time.perf_counter(); jax.block_until_ready(f(*a)); ts.append(time.perf_counter()-t)
    print(f"{name:12s} {np.median(ts)*1e3:9.3f} ms  (compile {c:.1f}s)", flush=True)
nb = jax.jit(lambda t: select_neighbours(dbj.condition, dbj.valid, t, 10, 0.15))(tg)
bench("neighbours", lambda t: select_neighbours(dbj.condition, dbj.valid, t, 10, 0.15), tg)
bench("pca_svd", lambda nb: pca_basis(dbj.q, dbj.duration, nb, 4), nb)
def gram_pca(nb):
    x = dbj.q[nb.index]  # (B,k,T,J)
    w = nb.mask[:, :, None, None].astype(x.dtype)
    mean = jnp.sum(w*x,1)/jnp.maximum(jnp.sum(w,1),1)
    c = (x-mean[:,None])*w
    g = jnp.einsum("bktj,bltj->bjkl", c, c)
    ev, u = jnp.linalg.eigh(g)
    comps = jnp.einsum("bjkl,bktj->bjlt", u[..., ::-1][..., :4], c)
    return mean, comps, ev
bench("pca_gram", gram_pca, nb)
final = dbj.q[nb.index,-1]
bench("ik20", lambda t,f: solve_ik(dyn, t, f[:,0], lo, hi, q_pref=f[:,0], iters=20), tg, final)
basis = jax.jit(lambda nb: pca_basis(dbj.q, dbj.duration, nb, 4))(nb)
J=7; z=jnp.zeros((B,J)); bc=Boundary(jnp.tile(lo[None]*0,(B,1)), final[:,0], z, z, jnp.full(B,0.7))
bench("solve_bc3", lambda b,bc: solve_boundary(b,bc,grid,3), basis, bc)
def dynf(q):
    qd,qdd=derivatives(grid,q,jnp.ones(q.shape[0])); return jax.vmap(jax.vmap(dyn.inverse))(q,qd,qdd)
bench("dynamics", dynf, basis.mean)
gen = make_online_generator(m.robot, dyn, grid)
bench("full", lambda t: gen(dbj, t, jnp.full(B,jnp.nan), jnp.tile(jnp.asarray(m.robot.rest[None],jnp.float32),(B,1))), tg)

"""The documentation site: it builds with warnings as errors (broken links, references and
snippets fail the build), every public name has a docstring and an API entry, the API page of
`simulate` holds its signature, its equations as math and working links, and the Python code
of the README and the guides runs."""

import html.parser
import inspect
import os
import pathlib
import re
import subprocess
import sys
import types

import numpy as np
import pytest

import jaxdyn

ROOT = pathlib.Path(__file__).resolve().parent.parent


def public_names():
    """The names `import jaxdyn` offers: classes, functions, constants and the `rotations`
    module (other modules are its own internals)."""
    names = []
    for name in dir(jaxdyn):
        value = getattr(jaxdyn, name)
        if name.startswith("_") or (isinstance(value, types.ModuleType)
                                    and name != "rotations"):
            continue
        names.append(name)
    return names


def test_every_public_name_has_a_docstring_and_an_api_entry():
    documented = set()
    for page in (ROOT / "docs" / "api").glob("*.md"):
        documented |= set(re.findall(r"^::: jaxdyn\.(\w+)", page.read_text(), re.M))
    names = public_names()
    assert len(names) > 60
    missing = [name for name in names if name not in documented]
    assert not missing, f"public names without an API entry in docs/api/: {missing}"
    stray = sorted(documented - set(names))
    assert not stray, f"API entries for names jaxdyn does not export: {stray}"
    for name in names:
        value = getattr(jaxdyn, name)
        if isinstance(value, type):
            # The class's own docstring: an equinox module (a dataclass) without one gets
            # "Name(field: type, ...)" generated, which documents nothing.
            own = value.__dict__.get("__doc__")
            assert not (own or "").startswith(f"{value.__name__}("), \
                f"jaxdyn.{name} has only the generated docstring {own!r}"
        elif isinstance(value, (types.FunctionType, types.ModuleType)):
            own = value.__doc__
        else:  # an instance (RESULTS): its class's
            own = inspect.getdoc(value)
        assert own and own.strip(), f"jaxdyn.{name} has no docstring"


class _Links(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.links, self.ids = [], set()

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if "id" in attrs:
            self.ids.add(attrs["id"])
        for key in ("href", "src"):
            if attrs.get(key):
                self.links.append(attrs[key])


def _parsed(path):
    parser = _Links()
    parser.feed(path.read_text())
    return parser


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    build = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
                           cwd=ROOT, capture_output=True, text=True, env=env, timeout=600)
    assert build.returncode == 0, build.stdout + build.stderr
    return out


def test_the_api_page_of_simulate_holds_its_signature_equations_and_working_links(site):
    page = site / "api" / "simulation" / "index.html"
    text = page.read_text()
    start = text.index('id="jaxdyn.simulate"')
    end = text.index('id="jaxdyn.Solution"')
    section = text[start:end]
    plain = re.sub(r"<[^>]+>", "", section)
    for argument in ("dynamics", "q0", "u0", "t1", "ts", "solver", "adjoint", "throw"):
        assert re.search(rf"\b{argument}\b", plain), argument
    # The equations as math: arithmatex's spans, which KaTeX renders in the browser.
    assert 'class="arithmatex"' in section
    assert r"M(t, q)\, \dot u = f(t, q, u)" in section
    # Every link of the page resolves: to a file of the site, and to an anchor on it.
    parser = _parsed(page)
    checked = 0
    for link in parser.links:
        if re.match(r"^[a-z]+:", link) or link.startswith("//"):
            continue  # external (none is needed offline; the site vendors KaTeX)
        target, _, anchor = link.partition("#")
        path = page if not target else (page.parent / target).resolve()
        if path.is_dir():
            path = path / "index.html"
        assert path.exists(), f"{link} on the simulate page leads nowhere"
        if anchor and path.suffix == ".html":
            assert anchor in _parsed(path).ids, f"{link}: no anchor {anchor}"
        checked += 1
    assert checked > 20


def test_the_site_renders_notebooks_examples_and_benchmarks(site):
    for name in [p.stem for p in (ROOT / "notebooks").glob("*.ipynb")]:
        page = site / "notebooks" / name / "index.html"
        assert page.exists(), name
        assert "jp-OutputArea" in page.read_text(), f"{name}: no outputs rendered"
    examples = (site / "examples" / "index.html").read_text()
    for script in (ROOT / "examples").glob("*.py"):
        assert script.name in examples, script.name
        # The figures a script writes are shown beside it (docs/figures holds a run's output).
        for figure in set(re.findall(r'"(\w+\.png)"', script.read_text())):
            assert f'src="../figures/{figure}"' in examples, f"{script.name}: {figure} not shown"
            assert (site / "figures" / figure).exists(), figure
    benchmarks = (site / "benchmarks" / "index.html").read_text()
    assert "work_precision.png" in benchmarks
    assert (site / "benchmarks" / "work_precision.png").exists()


# What the guides' fragments take from their surroundings (a system defined earlier on the
# page, data a user has): keyed by a line of the fragment, run before it.
_CONTEXT = {
    "plant = jaxdyn.Controlled(jaxdyn.Lagrangian(T, V), input_map=[0])": """
import scipy.linalg
def T(q, qd, p):
    return (0.5 * (p["M"] + p["m"]) * qd[0] ** 2 + p["m"] * p["l"] * qd[0] * qd[1]
            * jnp.cos(q[1]) + 0.5 * p["m"] * p["l"] ** 2 * qd[1] ** 2)
def V(q, p):
    return p["m"] * p["g"] * p["l"] * jnp.cos(q[1])
def lqr(A, B):
    A, B = np.asarray(A), np.asarray(B)
    riccati = scipy.linalg.solve_continuous_are(A, B, np.eye(4), np.eye(1))
    return jnp.asarray(B.T @ riccati)
p = dict(M=1.0, m=0.1, l=0.5, g=9.81)
q0, u0, ts = jnp.array([0.0, 0.3]), jnp.zeros(2), jnp.linspace(0.0, 6.0, 61)
""",
    "result = jaxdyn.fit(pendulum, experiments,": """
import fit_systems
pendulum, sigma = fit_systems.PENDULUM, 0.01
recordings = []
for q0 in ((0.5, -0.3), (-0.8, 0.4)):
    ts = np.linspace(0.0, 4.0, 41)
    angles = fit_systems.pendulum_data(q0, ts, 2.0, 1.5)[:, :2]
    noisy = angles + sigma * np.random.default_rng(0).standard_normal(angles.shape)
    recordings.append((ts, noisy, q0, (0.0, 0.0)))
""",
    "solver=jaxdyn.VariationalIntegrator()": """
pendulum, p, q0, qd0 = quickstart  # the pendulum of the README's first block
""",
    "q0s = np.stack([angles, angles / 2], axis=1)": """
def T(q, qd, p):
    v1 = p["l1"] * qd[0] * jnp.stack([jnp.cos(q[0]), jnp.sin(q[0])])
    v2 = v1 + p["l2"] * qd[1] * jnp.stack([jnp.cos(q[1]), jnp.sin(q[1])])
    return 0.5 * p["m1"] * v1 @ v1 + 0.5 * p["m2"] * v2 @ v2
def V(q, p):
    y1 = -p["l1"] * jnp.cos(q[0])
    return p["g"] * (p["m1"] * y1 + p["m2"] * (y1 - p["l2"] * jnp.cos(q[1])))
pendulum = jaxdyn.Lagrangian(T, V)
p = {"m1": 1.0, "m2": 1.0, "l1": 1.0, "l2": 1.0, "g": 9.81}
angles, ts = np.linspace(0.5, 2.5, 8), np.linspace(0.0, 10.0, 11)
q0, u0 = np.array([1.0, 0.5]), np.zeros(2)
""",
}


# The pages whose code runs, in the order a reader meets them (the site's navigation): the
# README's quickstart first, whose pendulum later pages reuse.
_PAGES = ["README.md", "docs/getting-started.md"] + [f"docs/guides/{name}.md" for name in (
    "formulations", "trees", "constraints", "events", "contact", "control", "identification",
    "batches", "stability", "speed", "errors")]


def test_the_pages_cover_every_guide():
    guides = {f"docs/guides/{p.name}" for p in (ROOT / "docs" / "guides").glob("*.md")}
    assert guides == set(_PAGES[2:])


@pytest.fixture(scope="module")
def guides():
    """Every Python block of the README and the guides, run in order in one namespace (as a
    reader pastes them), fragments after the context they assume; the namespace as each block
    left it, by (page, first line of the block). The block that joins several processes by
    `jax.distributed` is run for real by
    tests/test_batch.py::test_two_processes_with_jax_distributed_equal_one."""
    blocks = [(page, block) for page in _PAGES
              for block in re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S)]
    assert len(blocks) >= 12
    namespace = {}
    after, ran = {}, []
    with pytest.MonkeyPatch.context() as monkeypatch:
        monkeypatch.chdir(ROOT)
        monkeypatch.syspath_prepend(str(ROOT / "tests"))
        exec("import jax, jax.numpy as jnp, numpy as np, jaxdyn", namespace)
        for page, block in blocks:
            if "jax.distributed.initialize" in block:
                continue
            for key, context in _CONTEXT.items():
                if key in block:
                    exec(context, namespace)
            try:
                exec(compile(block, page, "exec"), namespace)
            except Exception as error:
                raise AssertionError(f"a block of {page} failed:\n{block}") from error
            if not ran:
                namespace["quickstart"] = tuple(namespace[k]
                                                for k in ("pendulum", "p", "q0", "qd0"))
            ran.append(page)
            after[page, block.splitlines()[0]] = dict(namespace)
    return blocks, ran, after


def test_the_guides_code_runs(guides):
    blocks, ran, _ = guides
    assert len(ran) == len(blocks) - 1


def test_the_contact_guides_anymal_settles_on_its_feet(guides):
    """The contact guide's ANYmal-C (example-robot-data), its joints held at a standing
    posture by PD control, dropped from 0.1 m above its standing height: after a second the
    feet's vertical forces sum to its weight (the URDF's masses), its feet do not slide and it
    stands at its height. (Its program, compiled for the guide, is shared here.)"""
    scene = guides[2]["docs/guides/contact.md",
                  'path = jaxdyn.example_robot_urdf("anymal_c_simple_description/urdf/'
                  'anymal.urdf")']
    tree, p, feet, sol, q0 = (scene[k] for k in ("tree", "p", "feet", "sol", "q0"))
    soles = [float(jaxdyn.frame_pose(tree, f.body, q0, p, point=f.point)[1][2]) - f.radius
             for f in feet]
    standing = float(q0[2]) - min(soles)  # the base's height with the lowest foot on the ground
    assert abs(float(q0[2]) - standing - 0.1) < 0.01  # dropped from 0.1 m above it
    weight = 9.81 * sum(float(link["mass"]) for link in p.values())
    np.testing.assert_allclose(np.sum(np.asarray(sol.contact.force[-1, :, 2])), weight,
                               rtol=1e-3)
    assert np.all(np.asarray(sol.contact.normal_force[0]) == 0)  # dropped from the air
    moved = np.asarray(sol.contact.position[-1, :, :2] - sol.contact.position[-2, :, :2])
    assert np.max(np.abs(moved)) < 1e-4  # feet planted, not sliding
    assert abs(float(sol.q[-1, 2]) - standing) < 0.02  # stands at its height

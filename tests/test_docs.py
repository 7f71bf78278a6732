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


# The pages whose code runs, in the order a reader meets them (the site's navigation): the
# README's quickstart first, whose pendulum later pages reuse.
_PAGES = ["README.md", "docs/getting-started.md"] + [f"docs/guides/{name}.md" for name in (
    "formulations", "trees", "constraints", "events", "contact", "control", "optimal_control",
    "identification",
    "batches", "stability", "speed", "errors")]


def test_the_pages_cover_every_guide():
    guides = {f"docs/guides/{p.name}" for p in (ROOT / "docs" / "guides").glob("*.md")}
    assert guides == set(_PAGES[2:])


@pytest.fixture(scope="module")
def guides():
    """Every Python block of the README and the guides, each page run top to bottom in a
    namespace of its own that starts empty (as a reader pastes the page into a fresh
    interpreter: nothing is supplied from outside the page; the process is shared only so
    that the compiled programs are); the namespace as each block left it, by (page, first line
    of the block). The block that joins several processes by `jax.distributed` is run for
    real by tests/test_batch.py::test_two_processes_with_jax_distributed_equal_one."""
    blocks = [(page, block) for page in _PAGES
              for block in re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S)]
    assert len(blocks) >= 12
    namespaces: dict = {}
    after, ran = {}, []
    with pytest.MonkeyPatch.context() as monkeypatch:
        monkeypatch.chdir(ROOT)
        for page, block in blocks:
            if "jax.distributed.initialize" in block:
                continue
            namespace = namespaces.setdefault(page, {"__name__": "__main__"})
            try:
                exec(compile(block, page, "exec"), namespace)
            except Exception as error:
                raise AssertionError(f"a block of {page} failed:\n{block}") from error
            ran.append(page)
            after[page, block.splitlines()[0]] = dict(namespace)
    return blocks, ran, after


def test_the_guides_code_runs(guides):
    """Every block ran, each page from an empty namespace; and each page's first block turns
    on 64-bit mode, as a fresh interpreter needs (the test process has it on already)."""
    blocks, ran, _ = guides
    assert len(ran) == len(blocks) - 1
    first = {}
    for page, block in blocks:
        first.setdefault(page, block)
    for page, block in first.items():
        assert 'jax.config.update("jax_enable_x64", True)' in block, page


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


def test_published_tables_are_their_recorded_results():
    """Every table of results on the README, the guides and the benchmarks page is the one
    generated from the CSV its benchmark script recorded (`python benchmarks/tables.py`
    rewrites them), and every recorded result is published somewhere."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
        import _results
    published = set()
    for page in _results.PAGES:
        text = (ROOT / page).read_text()
        assert _results.regenerated(text) == text, (
            f"{page}: a table disagrees with benchmarks/results; run python benchmarks/tables.py")
        published |= {m.group("name") for m in _results.REGION.finditer(text)}
    recorded = {path.stem for path in (ROOT / "benchmarks" / "results").glob("*.csv")}
    assert recorded and recorded == published


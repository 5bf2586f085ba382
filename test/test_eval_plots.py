"""Figures: each renders a readable PNG, and bad inputs are rejected with a clear error."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.image import imread

from controlled_islanding.evaluation import plots


def _image(path):
    image = imread(path)
    assert image.ndim == 3 and image.shape[0] > 200 and image.shape[1] > 200
    # A blank canvas would be a single colour.
    assert np.ptp(image[..., :3]) > 0.5
    return image


def test_rotor_angles_png(tmp_path):
    t = np.linspace(0.0, 5.0, 200)
    angles = np.vstack([np.sin(t), np.sin(t) + 0.1, -np.sin(t)])
    angles[1, 50:60] = np.nan
    out = plots.plot_rotor_angles(t, angles, ['A', 'B', 'C'], [0, 0, 1], tmp_path / 'sub' / 'rot.png',
                                  marks_s={'request': 4.0})
    _image(out)
    assert not [p for p in out.parent.iterdir() if p.name.startswith('.')]


def test_rotor_angles_rejects_transposed(tmp_path):
    t = np.linspace(0.0, 1.0, 20)
    with pytest.raises(plots.PlotError, match='transpose'):
        plots.plot_rotor_angles(t, np.zeros((20, 3)), ['A', 'B', 'C'], None, tmp_path / 'x.png')
    assert not (tmp_path / 'x.png').exists()


def test_distance_matrix_png_and_shape_check(tmp_path):
    d = np.array([[0.0, 1.0, 5.0], [1.0, 0.0, 4.0], [5.0, 4.0, 0.0]])
    _image(plots.plot_distance_matrix(d, ['A', 'B', 'C'], [1, 1, 0], tmp_path / 'd.png'))
    with pytest.raises(plots.PlotError, match='expected'):
        plots.plot_distance_matrix(d[:2], ['A', 'B', 'C'], None, tmp_path / 'e.png')
    with pytest.raises(plots.PlotError, match='group labels'):
        plots.plot_distance_matrix(d, ['A', 'B', 'C'], [0, 1], tmp_path / 'e.png')


class _Balance:
    def __init__(self, gen, load, shed):
        self.island_generation_mw, self.island_load_mw, self.island_shed_mw = gen, load, shed


def test_shedding_png_and_length_check(tmp_path):
    ok = _Balance([100.0, 50.0], [90.0, 70.0], [0.0, 20.0])
    _image(plots.plot_shedding({'a': ok, 'b': ok}, tmp_path / 's.png', title='t'))
    with pytest.raises(plots.PlotError, match='lengths'):
        plots.plot_shedding({'bad': _Balance([1.0], [1.0, 2.0], [0.0])}, tmp_path / 'f.png')
    with pytest.raises(plots.PlotError, match='no decisions'):
        plots.plot_shedding({}, tmp_path / 'g.png')


def test_network_png_and_unknown_ids(tmp_path):
    from controlled_islanding.core.grid import Grid

    grid = Grid.from_matpower('case14').with_outages(['1-5'])
    island = {b: int(b > 5) for b in grid.buses}
    _image(plots.plot_network(grid, island, ['4-5'], tmp_path / 'n.png', title='t'))
    layout = plots.network_layout(grid)
    assert layout.keys() == set(grid.buses)
    # The layout ignores branch status, so figures of one grid before and after outages line up.
    full = plots.network_layout(Grid.from_matpower('case14'))
    assert all(np.allclose(layout[b], full[b]) for b in grid.buses)
    with pytest.raises(plots.PlotError, match='cut branch ids'):
        plots.plot_network(grid, island, ['99-100'], tmp_path / 'x.png')
    with pytest.raises(plots.PlotError, match='not in grid'):
        plots.plot_network(grid, {999: 0}, [], tmp_path / 'x.png')

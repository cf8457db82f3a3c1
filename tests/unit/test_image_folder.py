"""image_publisher's folder without ROS: the image sets found in a folder (files or
sub-folders, in name order), unreadable and unmatched images, and the order sets are
shown in, once or looping."""

import cv2
import numpy as np
import pytest

from bag_tools.image_folder import ImageSetError, SetCycle, image_sets, read_grey


def write_grey(path, value):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((4, 6), value, np.uint8))


def test_sets_pair_the_n_th_file_of_each_camera_in_name_order(tmp_path):
    for i in (2, 1, 10):  # name order: 1, 10, 2
        write_grey(tmp_path / f'left{i}.png', i)
        write_grey(tmp_path / f'right{i}.png', 100 + i)
    (tmp_path / 'left_notes.txt').write_text('not an image')
    sets = image_sets(tmp_path, ['left', 'right'])
    assert [(s['left'].name, s['right'].name) for s in sets] == [
        ('left1.png', 'right1.png'),
        ('left10.png', 'right10.png'),
        ('left2.png', 'right2.png'),
    ]
    image = read_grey(sets[1]['right'])
    assert image.dtype == np.uint8 and image.shape == (4, 6) and np.all(image == 110)


def test_sub_folders_hold_a_camera_s_images(tmp_path):
    for name in ('left', 'right', 'aux'):
        write_grey(tmp_path / name / 'a.png', 1)
        write_grey(tmp_path / name / 'b.PNG', 2)
    sets = image_sets(tmp_path, ['left', 'right', 'aux'])
    assert [sorted(s) for s in sets] == [['aux', 'left', 'right']] * 2
    assert [s['aux'].name for s in sets] == ['a.png', 'b.PNG']


def test_unmatched_or_missing_images_are_refused_naming_the_counts(tmp_path):
    write_grey(tmp_path / 'left1.png', 1)
    write_grey(tmp_path / 'left2.png', 2)
    write_grey(tmp_path / 'right1.png', 1)
    with pytest.raises(ImageSetError, match='found left 2, right 1'):
        image_sets(tmp_path, ['left', 'right'])
    with pytest.raises(ImageSetError, match='found left 2, aux 0'):
        image_sets(tmp_path, ['left', 'aux'])
    with pytest.raises(ImageSetError, match='is not a directory'):
        image_sets(tmp_path / 'nowhere', ['left'])
    (tmp_path / 'broken.png').write_bytes(b'not a png')
    with pytest.raises(ImageSetError, match='cannot read image'):
        read_grey(tmp_path / 'broken.png')


def test_sets_are_shown_once_in_order_or_again_and_again():
    once = SetCycle(3, loop=False)
    shown = [once.next() for _ in range(5)]
    assert shown == [0, 1, 2, None, None] and once.done
    looping = SetCycle(2, loop=True)
    assert [looping.next() for _ in range(5)] == [0, 1, 0, 1, 0]
    assert not looping.done
    fresh = SetCycle(2, loop=False)
    fresh.next()
    assert not fresh.done  # one set still to show

"""MemoryDirectory against the file system: every way out of the folder is refused, every way
in works; SkillMemory.read refuses what is not a regular file and what declares too much."""
import os
import zipfile

import numpy as np
import pytest

from psl_memory.memory_directory import MemoryDirectory, MemoryPathError
from psl_memory.skill_memory import MemoryFileError, SkillMemory


@pytest.fixture()
def folder(tmp_path):
    root = tmp_path / 'memory'
    return MemoryDirectory(root), root, tmp_path


def test_names_and_paths_inside_resolve_into_the_folder(folder):
    files, root, _ = folder
    assert files.for_writing('a.npz') == root / 'a.npz'
    assert files.for_writing('sub/b.npz') == root / 'sub' / 'b.npz' and (root / 'sub').is_dir()
    assert files.for_writing(str(root / 'c.npz')) == root / 'c.npz'
    assert files.resolve('sub/../d.npz') == root / 'd.npz'        # stays inside


@pytest.mark.parametrize('name', ['../x.npz', 'sub/../../x.npz', '/etc/hostname', '..', '.',
                                  ''])
def test_every_way_out_is_refused(folder, name):
    files, root, tmp_path = folder
    with pytest.raises(MemoryPathError):
        files.for_writing(name)
    assert not (tmp_path / 'x.npz').exists()


def test_links_fifos_devices_and_folders_are_refused(folder):
    files, root, tmp_path = folder
    target = tmp_path / 'target.npz'
    target.write_bytes(b'keep')
    (root / 'link.npz').symlink_to(target)
    (root / 'dirlink').symlink_to(tmp_path)
    os.mkfifo(root / 'pipe.npz')
    (root / 'folder').mkdir()
    for name, words in (('link.npz', 'symbolic link'), ('dirlink/target.npz', 'symbolic link'),
                        ('pipe.npz', 'not a regular file'), ('folder', 'is a directory')):
        for method in (files.for_writing, files.for_reading):
            with pytest.raises(MemoryPathError, match=words):
                method(name)
    with pytest.raises(MemoryPathError, match='no such file'):
        files.for_reading('absent.npz')
    assert target.read_bytes() == b'keep'


def test_read_refuses_without_following_links_or_waiting_on_a_fifo(tmp_path):
    good = tmp_path / 'good.npz'
    SkillMemory().save(good)
    link = tmp_path / 'link.npz'
    link.symlink_to(good)
    os.mkfifo(tmp_path / 'pipe.npz')
    with pytest.raises(MemoryFileError, match='cannot be opened'):
        SkillMemory.read(link)                      # O_NOFOLLOW: a link is not read through
    with pytest.raises(MemoryFileError, match='not a regular file'):
        SkillMemory.read(tmp_path / 'pipe.npz')     # O_NONBLOCK: no writer needed to refuse
    if os.path.exists('/dev/null'):
        with pytest.raises(MemoryFileError, match='not a regular file'):
            SkillMemory.read('/dev/null')
    assert SkillMemory.read(good).skills == {}


def test_save_never_replaces_what_is_not_a_regular_file(tmp_path):
    target = tmp_path / 'target.npz'
    target.write_bytes(b'keep')
    link = tmp_path / 'link.npz'
    link.symlink_to(target)
    with pytest.raises(OSError, match='not a regular file'):
        SkillMemory().save(link)
    assert link.is_symlink() and target.read_bytes() == b'keep'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['link.npz', 'target.npz']   # no temp


def test_declared_sizes_are_checked_before_anything_is_read(tmp_path):
    """Limits from the archive's directory: the file's size and its members' declared sizes."""
    memory = SkillMemory()
    memory.create('s', [0.0], [1.0], np.zeros(3))
    path = tmp_path / 'memory.npz'
    memory.save(path)
    declared = sum(m.file_size for m in zipfile.ZipFile(path).infolist())
    enough = max(declared, path.stat().st_size)
    assert SkillMemory.read(path, max_bytes=enough).skills.keys() == {'s'}
    with pytest.raises(MemoryFileError, match='more than the limit'):
        SkillMemory.read(path, max_bytes=enough - 1)
    # a small file that declares a large array: refused from its directory, nothing inflated
    bomb = tmp_path / 'bomb.npz'
    with zipfile.ZipFile(bomb, 'w', zipfile.ZIP_DEFLATED) as archive:
        with archive.open('big.npy', 'w', force_zip64=True) as member:
            for _ in range(64):
                member.write(bytes(2**20))
    assert bomb.stat().st_size < 2**20
    with pytest.raises(MemoryFileError, match='declares 1 arrays of 67108864 bytes'):
        SkillMemory.read(bomb, max_bytes=2**20)

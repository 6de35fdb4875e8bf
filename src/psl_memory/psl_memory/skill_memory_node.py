"""The skill memory node: named parameterized skills behind services.

Serves ``~/query`` (psl_msgs/QuerySkill: theta = PS(tau) and its per-dimension predictive
variance), ``~/add_sample`` (AddSample), ``~/complete`` (CompletePattern: associative completion
of [tau, theta] with the known dimensions clamped), ``~/create_skill`` (CreateSkill: a skill
with a task's tau ranges and theta reference), ``~/save`` and ``~/load`` (SaveMemory,
LoadMemory: one versioned file, named inside the node's ``memory_dir``) and ``~/info``
(std_srvs/Trigger: the skills as JSON).
The node knows no tasks: a task's skill is created by whoever knows the task (``psl up``, the
learner) through ``~/create_skill``, or by its first sample. Every bad request gets ``success=false`` and a message saying what was wrong; the memory
is unchanged and the node keeps serving.

Memory files live in one folder, ``memory_dir`` (default: the working directory the node was
started in, i.e. where ``psl up`` ran): ``~/save`` and ``~/load`` take a file name or a path
inside it and refuse anything else — a path leading out (``..``, an absolute path elsewhere),
a symbolic link on the way, a file that is not a regular file (directory, device, FIFO) —
without creating, replacing or reading anything (`psl_memory.memory_directory`). A file is
checked against ``max_file_megabytes`` (its size and the sizes its archive declares) before an
array is read, and read outside the service lock, so the other services go on answering. With ``autosave_path`` set, the memory is loaded from
that file at start (if it exists) and written back after every added sample, so a killed node
restarts with everything it had learned.
"""
from __future__ import annotations

import dataclasses
import json
import os
import threading

import numpy as np
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from std_srvs.srv import Trigger

from psl_msgs.srv import (AddSample, CompletePattern, CreateSkill, LoadMemory, QuerySkill,
                          SaveMemory)
from psl_memory.skill_config import SkillConfig
from psl_memory.memory_directory import MemoryDirectory, MemoryPathError
from psl_memory.skill_memory import MAX_FILE_BYTES, MemoryFileError, SkillMemory
from psl_ros.node_main import run_node
from psl_ros.service import create_service


class SkillMemoryNode(Node):

    def __init__(self):
        super().__init__('skill_memory')
        defaults = SkillConfig()
        for name, default, text in (
                ('readout', defaults.readout, 'ridge | rls | incremental_ridge | bayes'),
                ('n_hidden', defaults.n_hidden, 'hidden neurons of the ELM'),
                ('regularization', defaults.regularization, 'ridge factor / prior precision'),
                ('forgetting', defaults.forgetting, 'RLS forgetting factor, 0 < lambda <= 1'),
                ('seed', defaults.seed, 'seed of the random hidden layer'),
                ('alpha', defaults.alpha, 'slope of the hidden sigmoid'),
                ('associative', defaults.associative,
                 'aelm | arbf | rbm | hopfield (rbm, hopfield: baselines)'),
                ('estimate_precisions', defaults.estimate_precisions,
                 'bayes: estimate the prior and noise precisions by evidence maximisation'),
                ('noise_precision', defaults.noise_precision, 'bayes: noise precision beta'),
                ('completion_tolerance', defaults.completion_tolerance,
                 'recall stops when no entry moves more than this (normalised units)'),
                ('completion_max_iterations', defaults.completion_max_iterations,
                 'recall iteration cap'),
                ('memory_dir', '', "the folder of the memory files ('' = the working "
                                   'directory); save, load and autosave stay inside it'),
                ('max_file_megabytes', MAX_FILE_BYTES / 2**20,
                 'largest memory file (and declared array content) that is read'),
                ('autosave_path', '', 'memory file (inside memory_dir) loaded at start and '
                                      'written after every sample; empty = no autosave')):
            self.declare_parameter(name, default, ParameterDescriptor(description=text,
                                                                      read_only=True))
        self.config = SkillConfig(**{field.name: self.get_parameter(field.name).value
                                     for field in dataclasses.fields(SkillConfig)})
        self.files = MemoryDirectory(self.get_parameter('memory_dir').value or os.getcwd())
        self.max_bytes = int(self.get_parameter('max_file_megabytes').value * 2**20)
        autosave = self.get_parameter('autosave_path').value
        self.autosave = self.files.for_writing(autosave) if autosave else None
        self._lock = threading.Lock()
        self.memory = self._initial_memory()
        for name, srv, callback in (('~/query', QuerySkill, self.on_query),
                                    ('~/add_sample', AddSample, self.on_add),
                                    ('~/complete', CompletePattern, self.on_complete),
                                    ('~/create_skill', CreateSkill, self.on_create),
                                    ('~/save', SaveMemory, self.on_save),
                                    ('~/load', LoadMemory, self.on_load),
                                    ('~/info', Trigger, self.on_info)):
            create_service(self, srv, name, callback)
        self.get_logger().info(f'skills: {json.dumps(self.memory.info())}')

    def _initial_memory(self) -> SkillMemory:
        if self.autosave is not None and self.autosave.is_file():
            # a corrupt file stops the node here
            memory = SkillMemory.read(self.autosave, self.max_bytes)
            self.get_logger().info(f'restored the memory from {self.autosave}')
            return memory
        return SkillMemory(self.config)

    # -- services -----------------------------------------------------------------------------
    def _serve(self, response, work):
        """Run `work` under the lock; any error becomes success=false with its message."""
        try:
            with self._lock:
                message = work()
            response.success, response.message = True, message or 'ok'
        except (KeyError, ValueError, OSError, RuntimeError) as exc:
            text = exc.args[0] if isinstance(exc, KeyError) and exc.args else str(exc)
            response.success, response.message = False, str(text)
        return response

    def on_query(self, request, response):
        def work():
            theta, var = self.memory.get(request.skill).query(np.asarray(request.tau))
            response.theta = theta.tolist()
            response.variance = [] if var is None else var.tolist()
            return '' if var is not None else 'this readout has no predictive variance'
        return self._serve(response, work)

    def on_add(self, request, response):
        def work():
            response.num_samples = self.memory.add(request.skill, np.asarray(request.tau),
                                                   np.asarray(request.theta))
            if self.autosave is not None:
                self.memory.save(self.autosave)
            return f'{response.num_samples} samples'
        return self._serve(response, work)

    def on_create(self, request, response):
        def work():
            existed = request.skill in self.memory.skills and not request.replace
            skill = self.memory.create(request.skill, np.asarray(request.tau_low),
                                       np.asarray(request.tau_high),
                                       np.asarray(request.theta_reference), exist_ok=True,
                                       replace=request.replace)
            response.created, response.num_samples = not existed, skill.num_samples
            if existed:
                return (f'skill {request.skill!r} exists ({skill.num_samples} samples); kept '
                        'as it is')
            if self.autosave is not None:
                self.memory.save(self.autosave)
            return (f'created skill {request.skill!r} ({skill.tau_dim} task, '
                    f'{skill.theta_dim} policy parameters)')
        return self._serve(response, work)

    def on_complete(self, request, response):
        def work():
            skill = self.memory.get(request.skill)
            size = skill.tau_dim + skill.theta_dim
            if len(request.known) != size:
                raise ValueError(f'known needs {size} entries (tau then theta), got '
                                 f'{len(request.known)}')
            result = skill.complete(np.asarray(request.pattern), np.asarray(request.known))
            response.pattern = result.pattern.tolist()
            state = 'converged' if result.converged else 'did NOT converge'
            return f'{state} after {result.iterations} iterations (residual {result.residual:.2e})'
        return self._serve(response, work)

    def on_save(self, request, response):
        def work():
            path = self.files.for_writing(request.path)
            self.memory.save(path)
            return f'saved {len(self.memory.skills)} skills to {path}'
        return self._serve(response, work)

    def on_load(self, request, response):
        # read and checked outside the lock: a large or crafted file does not stall the
        # other services; the memory is swapped under the lock
        try:
            path = self.files.for_reading(request.path)
            memory = SkillMemory.read(path, self.max_bytes)
        except (MemoryPathError, MemoryFileError) as exc:
            response.success = False
            response.message = f'{exc}; the memory in use is unchanged'
            return response

        def work():
            self.memory = memory
            return f'loaded {len(memory.skills)} skills from {path}'
        return self._serve(response, work)

    def on_info(self, request, response):
        with self._lock:
            response.success, response.message = True, json.dumps(self.memory.info())
        return response


def main(args=None):
    run_node(SkillMemoryNode, args)


if __name__ == '__main__':
    main()

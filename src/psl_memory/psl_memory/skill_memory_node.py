"""The skill memory node: named parameterized skills behind services.

Serves ``~/query`` (psl_msgs/QuerySkill: theta = PS(tau) and its per-dimension predictive
variance), ``~/add_sample`` (AddSample), ``~/complete`` (CompletePattern: associative completion
of [tau, theta] with the known dimensions clamped), ``~/create_skill`` (CreateSkill: a skill
with a task's tau ranges and theta reference), ``~/save`` and ``~/load`` (SaveMemory,
LoadMemory: one versioned file, named inside the node's ``memory_dir``; a load adds the file's
skills, replacing skills of the same name only with ``replace``), ``~/claim`` (ClaimSkill: a
learning session's claim on its skill) and ``~/info`` (std_srvs/Trigger: the skills as JSON).
The node knows no tasks: a task's skill is created by whoever knows the task (``psl up``, the
learner) through ``~/create_skill``, or by its first sample. Every bad request gets
``success=false`` and a message saying what was wrong; the memory is unchanged and the node
keeps serving. What a request may make the node hold is bounded (`psl_memory.memory_limits`,
a parameter per bound).

A skill a learning session has claimed takes samples, a replacement and a load over it only
from the claim's owner (a node's fully qualified name), until the owner releases it or leaves
the graph: a ``psl memory load`` during a session is refused, instead of swapping the skill
under it.

Memory files live in one folder, ``memory_dir`` (default: the working directory the node was
started in, i.e. where ``psl up`` ran): ``~/save`` and ``~/load`` take a file name or a path
inside it and refuse anything else — a path leading out (``..``, an absolute path elsewhere),
a symbolic link on the way, a file that is not a regular file (directory, device, FIFO) —
without creating, replacing or reading anything (`psl_memory.memory_directory`). A file is
checked against ``max_file_bytes`` (its size and the sizes its archive declares) and
``max_skills`` (the arrays it holds) before an array is read, and read outside the service
lock, so the other services go on answering. With ``autosave_path`` set, the memory is loaded
from that file at start (if it exists) and written back after every added sample, so a killed
node restarts with everything it had learned.
"""
from __future__ import annotations

import json
import os
import threading

import numpy as np
from rclpy.node import Node

from psl_memory.skill_config import SkillConfig
from psl_memory.memory_directory import MemoryDirectory, MemoryFiles, MemoryPathError
from psl_memory.memory_limits import MemoryLimits
from psl_memory.skill_memory import MemoryFileError, SkillMemory
from psl_ros.client import MEMORY_SERVICES
from psl_ros.node_main import run_node
from psl_ros.parameters import declare
from psl_ros.service import create_service


class SkillMemoryNode(Node):

    def __init__(self):
        super().__init__('skill_memory')
        self.config = declare(self, SkillConfig)
        self.limits = declare(self, MemoryLimits)  # what one request may make the node hold
        files = declare(self, MemoryFiles)
        self.files = MemoryDirectory(files.memory_dir or os.getcwd())
        self.autosave = (self.files.for_writing(files.autosave_path) if files.autosave_path
                         else None)
        self._lock = threading.Lock()
        self.memory = self._initial_memory()
        self.claims: dict[str, str] = {}        # skill -> owner (a node's full name)
        callbacks = {'query': self.on_query, 'add_sample': self.on_add,
                     'complete': self.on_complete, 'create_skill': self.on_create,
                     'save': self.on_save, 'load': self.on_load, 'claim': self.on_claim,
                     'info': self.on_info}
        for name, srv in MEMORY_SERVICES.items():   # the types: one table, client and node
            create_service(self, srv, f'~/{name}', callbacks[name])
        self.get_logger().info(f'skills: {json.dumps(self.memory.info())}')

    def _initial_memory(self) -> SkillMemory:
        if self.autosave is not None and self.autosave.is_file():
            # a corrupt file stops the node here
            memory = SkillMemory.read(self.autosave, limits=self.limits)
            self.get_logger().info(f'restored the memory from {self.autosave}')
            return memory
        return SkillMemory(self.config, self.limits)

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

    # -- claims (ClaimSkill) --------------------------------------------------------------------
    def _owner_alive(self, owner: str) -> bool:
        return owner in {(ns.rstrip('/') + '/' + name) for name, ns in
                         self.get_node_names_and_namespaces()}

    def _claimed_by_another(self, skill: str, owner: str) -> str:
        """The live owner of `skill` if it is not `owner`, else '' (a claim whose owner has
        left the graph lapses here)."""
        holder = self.claims.get(skill)
        if holder is None or holder == owner:
            return ''
        if not self._owner_alive(holder):
            self.get_logger().warning(f'claim of {skill!r} by {holder} lapsed: it has left')
            del self.claims[skill]
            return ''
        return holder

    def _check_claim(self, skill: str, owner: str, doing: str) -> None:
        holder = self._claimed_by_another(skill, owner)
        if holder:
            raise ValueError(f'skill {skill!r} is being learned by {holder} (claimed): '
                             f'{doing} refused until its session ends')

    def on_claim(self, request, response):
        def work():
            if not request.owner:
                raise ValueError('a claim needs an owner (a node\'s fully qualified name)')
            if request.release:
                if self.claims.get(request.skill) == request.owner:
                    del self.claims[request.skill]
                    return f'released {request.skill!r}'
                return f'{request.skill!r} was not claimed by {request.owner}'
            self._check_claim(request.skill, request.owner, 'a claim')
            self.memory.check_new_skill(request.skill, 0, 0)    # the name's bounds
            self.claims[request.skill] = request.owner
            return f'{request.skill!r} claimed by {request.owner}'
        return self._serve(response, work)

    def on_add(self, request, response):
        def work():
            self._check_claim(request.skill, request.owner, 'adding a sample')
            response.num_samples = self.memory.add(request.skill, np.asarray(request.tau),
                                                   np.asarray(request.theta))
            if self.autosave is not None:
                self.memory.save(self.autosave)
            return f'{response.num_samples} samples'
        return self._serve(response, work)

    def on_create(self, request, response):
        def work():
            if request.replace:
                self._check_claim(request.skill, request.owner, 'replacing it')
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
            memory = SkillMemory.read(path, limits=self.limits)
        except (MemoryPathError, MemoryFileError, OSError, ValueError) as exc:
            response.success = False
            response.message = f'{exc}; the memory in use is unchanged'
            return response

        def work():
            for name in memory.skills:
                self._check_claim(name, request.owner, 'loading over it')
            replaced = sorted(set(memory.skills) & set(self.memory.skills))
            names = self.memory.merge(memory, replace=request.replace)
            if self.autosave is not None:
                self.memory.save(self.autosave)
            return (f'loaded {len(names)} skills from {path}'
                    + (f' (replaced {", ".join(map(repr, replaced))})' if replaced else '')
                    + f'; the memory holds {len(self.memory.skills)}')
        return self._serve(response, work)

    def on_info(self, request, response):
        with self._lock:
            response.success, response.message = True, json.dumps(self.memory.info())
        return response


def main(args=None):
    run_node(SkillMemoryNode, args)


if __name__ == '__main__':
    main()
